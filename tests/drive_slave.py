"""A CiA 402 drive hil did not write: canopen's ``LocalNode`` with an object dictionary of its
own, different from hil's emulator where a real drive would be: a 17-bit encoder, a rated
current of 2 A, CST only, all four PDOs valid at power-on, no RPDO2-4/TPDO3-4 at all, and the
CiA 301 remapping rules enforced (a valid PDO's COB-ID and mapping cannot change; a mapping
entry must name a mappable object of the right size). Its SYNC counter echo is object 0x2100;
0x2003 and 0x2005 are objects of its own (digital outputs, a brake release delay), where hil's
emulator has its disturbance torque and time base.

Made to lack what vendors' drives lack (``dictionary(without=...)``: a maxon EPOS4 has no
0x608F and no 0x6075; any optional object), to support CSP, CSV, PP, PV and HM too
(``modes``: its own position loop towards 0x607A, velocity loop towards 0x60FF; a trapezoidal
profile by 0x6081/0x6083/0x6084 with the new-set-point handshake, a velocity ramp; homing
methods 35 and 37, where the axis stands, any other one a homing error: it has no switches),
and built from an EDS file
(``IndependentSlave(od=import_od(F))``: the dictionary a vendor's file describes).

SDO, NMT and the heartbeat producer are canopen's; this module adds what a LocalNode does not
do: the cyclic path (RPDO latched on SYNC, a simple axis advanced one period, the TPDOs of the
current maps sent), and the CiA 402 state machine after canopen's ``State402`` tables. Every
TPDO pair it sends is logged with the number of the SYNC it answers (1 = the first SYNC after
NMT start), so a test can hold the master's feedback against it.

``behind_at``: the slave falls one cycle behind at that SYNC: it holds its answer to it back
until the next SYNC comes, then sends it just before that SYNC's own answer. However late the
master waits, that answer lands after the next SYNC: what a drive that fell behind does, with
nothing left to timing.

Run alone (another process): ``python tests/drive_slave.py URL NODE LOG.json [--behind-at N]``;
it serves until SIGTERM, then writes its log.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
from typing import Any

import canopen
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable
from canopen.objectdictionary import datatypes as dt
from canopen.profiles.p402 import State402
from canopen.sdo import SdoAbortedError

INCREMENTS = 1 << 17
RATED_MA = 2000
ECHO = 0x2100
VENDOR_OUTPUTS, VENDOR_BRAKE_DELAY = 0x2003, 0x2005  # where hil's emulator has its hooks
SUPPORTED = 0x0200  # CST only
CST, CSP, CSV, PP, PV, HM = 10, 8, 9, 1, 3, 6
SUPPORTED_BITS = {CST: 0x0200, CSP: 0x0080, CSV: 0x0100, PP: 0x0001, PV: 0x0004, HM: 0x0020}
LOOP_HZ = 50.0  # CSP: its position loop's natural frequency (critically damped)
PERIOD_S = 500e-6
GAIN_DEG_S2_PER_MA = 400.0  # axis acceleration per mA (a plain inertia)

RPDO1 = [(0x6040, 0, 16), (0x6071, 0, 16)]
TPDO1 = [(0x6041, 0, 16), (0x6064, 0, 32)]
TPDO2 = [(0x606C, 0, 32), (0x6077, 0, 16)]


def _var(name: str, index: int, sub: int, kind: int, access: str, default: Any = 0,
         mappable: bool = False) -> ODVariable:
    var = ODVariable(name, index, sub)
    var.data_type, var.access_type, var.default, var.pdo_mappable = kind, access, default, mappable
    return var


def _record(od: ObjectDictionary, name: str, index: int, members: list[ODVariable],
            array: bool = False) -> None:
    record = ODArray(name, index) if array else ODRecord(name, index)
    for member in members:
        record.add_member(member)
    od.add_object(record)


def _pdo(od: ObjectDictionary, comm: int, mapping: int, cob: int, entries: list) -> None:
    _record(od, f"PDO {comm:04X}", comm, [
        _var("count", comm, 0, dt.UNSIGNED8, "const", 2),
        _var("COB-ID", comm, 1, dt.UNSIGNED32, "rw", cob),
        _var("type", comm, 2, dt.UNSIGNED8, "rw", 1)])
    _record(od, f"map {mapping:04X}", mapping, [
        _var("count", mapping, 0, dt.UNSIGNED8, "rw", len(entries)),
        *(_var(f"entry {k}", mapping, k, dt.UNSIGNED32, "rw",
               i << 16 | s << 8 | b) for k, (i, s, b) in enumerate(entries, 1)),
        *(_var(f"entry {k}", mapping, k, dt.UNSIGNED32, "rw", 0)
          for k in range(len(entries) + 1, 5))])


def dictionary(node_id: int, max_current_permille: int | None = None, *,
               without: tuple[int, ...] = (), modes: tuple[int, ...] = (CST,)
               ) -> ObjectDictionary:
    """The slave's object dictionary; with ``max_current_permille``, a 0x6073 max current of
    its own (per mille of the rated current); ``without``: objects it lacks; ``modes``: the
    modes 0x6502 lists (CST, CSP: 0x607A then)."""
    od = ObjectDictionary()
    od.node_id = node_id
    add = od.add_object
    add(_var("Device type", 0x1000, 0, dt.UNSIGNED32, "ro", 0x0002_0192))
    add(_var("Error register", 0x1001, 0, dt.UNSIGNED8, "ro", 0))
    add(_var("Communication cycle period", 0x1006, 0, dt.UNSIGNED32, "rw", 0))
    add(_var("Device name", 0x1008, 0, dt.VISIBLE_STRING, "const", "independent 402 slave"))
    _record(od, "Consumer heartbeat", 0x1016, [
        _var("count", 0x1016, 0, dt.UNSIGNED8, "const", 1),
        _var("time 1", 0x1016, 1, dt.UNSIGNED32, "rw", 0)], array=True)
    add(_var("Producer heartbeat time", 0x1017, 0, dt.UNSIGNED16, "rw", 0))
    _record(od, "Identity", 0x1018, [
        _var("count", 0x1018, 0, dt.UNSIGNED8, "const", 4),
        _var("Vendor-ID", 0x1018, 1, dt.UNSIGNED32, "ro", 0x00C0FFEE),
        _var("Product code", 0x1018, 2, dt.UNSIGNED32, "ro", 17),
        _var("Revision", 0x1018, 3, dt.UNSIGNED32, "ro", 3),
        _var("Serial", 0x1018, 4, dt.UNSIGNED32, "ro", 4711)])
    add(_var("Synchronous counter overflow value", 0x1019, 0, dt.UNSIGNED8, "rw", 0))
    _pdo(od, 0x1400, 0x1600, 0x200 + node_id, RPDO1)
    _pdo(od, 0x1800, 0x1A00, 0x180 + node_id, TPDO1)
    _pdo(od, 0x1801, 0x1A01, 0x280 + node_id, TPDO2)
    add(_var("SYNC counter of this answer", ECHO, 0, dt.UNSIGNED8, "ro", 0, True))
    # the vendor's own objects at the indices of hil's emulator's hooks, meaning other things
    add(_var("Digital outputs", VENDOR_OUTPUTS, 0, dt.INTEGER16, "rw", 0))
    add(_var("Brake release delay [ms]", VENDOR_BRAKE_DELAY, 0, dt.UNSIGNED32, "rw", 200))
    add(_var("Error code", 0x603F, 0, dt.UNSIGNED16, "ro", 0))
    add(_var("Controlword", 0x6040, 0, dt.UNSIGNED16, "rw", 0, True))
    add(_var("Statusword", 0x6041, 0, dt.UNSIGNED16, "ro", 0, True))
    add(_var("Quick stop option", 0x605A, 0, dt.INTEGER16, "rw", 2))
    add(_var("Modes of operation", 0x6060, 0, dt.INTEGER8, "rw", 0))
    add(_var("Modes of operation display", 0x6061, 0, dt.INTEGER8, "ro", 0))
    add(_var("Position actual", 0x6064, 0, dt.INTEGER32, "ro", 0, True))
    add(_var("Velocity actual", 0x606C, 0, dt.INTEGER32, "ro", 0, True))
    add(_var("Target torque", 0x6071, 0, dt.INTEGER16, "rw", 0, True))
    add(_var("Max torque", 0x6072, 0, dt.UNSIGNED16, "rw", 1000))
    if max_current_permille is not None:
        add(_var("Max current", 0x6073, 0, dt.UNSIGNED16, "ro", max_current_permille))
    add(_var("Rated current", 0x6075, 0, dt.UNSIGNED32, "ro", RATED_MA))
    add(_var("Torque actual", 0x6077, 0, dt.INTEGER16, "ro", 0, True))
    _record(od, "Position encoder resolution", 0x608F, [
        _var("count", 0x608F, 0, dt.UNSIGNED8, "const", 2),
        _var("increments", 0x608F, 1, dt.UNSIGNED32, "ro", INCREMENTS),
        _var("motor revolutions", 0x608F, 2, dt.UNSIGNED32, "ro", 1)])
    if {CSP, PP} & set(modes):
        add(_var("Target position", 0x607A, 0, dt.INTEGER32, "rw", 0, True))
    if {CSV, PV} & set(modes):
        add(_var("Target velocity", 0x60FF, 0, dt.INTEGER32, "rw", 0, True))
    if {PP, PV} & set(modes):  # 90 deg/s, 360 deg/s^2, a window of 0.1 deg
        for index, name, default in ((0x6081, "Profile velocity", INCREMENTS // 4),
                                     (0x6083, "Profile acceleration", INCREMENTS),
                                     (0x6084, "Profile deceleration", INCREMENTS),
                                     (0x6067, "Position window", INCREMENTS // 3600)):
            add(_var(name, index, 0, dt.UNSIGNED32, "rw", default))
    if HM in modes:
        add(_var("Homing method", 0x6098, 0, dt.INTEGER8, "rw", 0))
        add(_var("Home offset", 0x607C, 0, dt.INTEGER32, "rw", 0))
        _record(od, "Homing speeds", 0x6099, [
            _var("count", 0x6099, 0, dt.UNSIGNED8, "const", 2),
            _var("switch", 0x6099, 1, dt.UNSIGNED32, "rw", INCREMENTS // 12),
            _var("zero", 0x6099, 2, dt.UNSIGNED32, "rw", INCREMENTS // 72)], array=True)
        add(_var("Homing acceleration", 0x609A, 0, dt.UNSIGNED32, "rw", INCREMENTS))
    add(_var("Supported drive modes", 0x6502, 0, dt.UNSIGNED32, "ro",
             sum(SUPPORTED_BITS[mode] for mode in modes)))
    for index in without:
        del od[index]
    return od


class IndependentSlave:
    """The drive on ``network`` (a connected canopen Network) as node ``node_id``."""

    def __init__(self, network: canopen.Network, node_id: int = 3, *,
                 behind_at: int | None = None,
                 max_current_permille: int | None = None,
                 od: ObjectDictionary | None = None) -> None:
        self.network, self.node_id = network, node_id
        self.behind_at = behind_at
        self.held: list[tuple[int, bytes]] = []  # an answer held back (behind_at)
        self.node = canopen.LocalNode(node_id, od or dictionary(node_id, max_current_permille))
        self.od = self.node.object_dictionary
        self.node.add_write_callback(self._on_write)
        self.node.add_read_callback(self._on_read)
        network.add_node(self.node)
        network.subscribe(0x080, self._on_sync)
        network.subscribe(0x000, self._on_nmt)
        self.state = "SWITCH ON DISABLED"
        self.position = 0.0      # degrees, multi-turn
        self.velocity = 0.0      # degrees per second
        self.current_ma = 0.0
        self.controlword = 0
        self.mode_bits = 0       # statusword bits 10, 12, 13 of PP and HM
        self.pp_target: float | None = None  # degrees, its own multi-turn frame
        self.latched: bytes | None = None
        self.syncs = 0           # SYNCs since NMT start
        self.log: list[dict[str, Any]] = []
        self.writes: list[tuple[int, int, bytes]] = []  # every SDO download, in order
        # objects it answers with abort 0x06020000 (no such object) though it has them
        self.refuses: tuple[int, ...] = ()
        self.lock = threading.Lock()
        self.node.nmt.state = "PRE-OPERATIONAL"

    # -- values --------------------------------------------------------------------------
    def value(self, index: int, sub: int = 0) -> int:
        return int(self.od[index].decode_raw(self.node.get_data(index, sub))
                   if sub == 0 and not hasattr(self.od[index], "subindices") else
                   self.od[index][sub].decode_raw(self.node.get_data(index, sub)))

    def written(self, index: int, sub: int = 0) -> list[int]:
        """Every value a master downloaded to ``index:sub``, in order (a run's setting, then
        the drive's own put back when the run let it go)."""
        var = self.od[index][sub] if hasattr(self.od[index], "subindices") else self.od[index]
        return [int(var.decode_raw(data)) for i, s, data in self.writes
                if (i, s) == (index, sub)]

    def _live(self, index: int) -> int | None:
        if index == 0x6041:
            _mask, word = State402.SW_MASK[self.state]
            return word | 0x0200 | (0x0010 if self.state != "NOT READY TO SWITCH ON" else 0) \
                | self.mode_bits
        if index == 0x6064:
            return round(self.position / 360.0 * INCREMENTS) % INCREMENTS
        if index == 0x606C:
            return round(self.velocity / 360.0 * INCREMENTS)
        if index == 0x6077:
            return round(self.current_ma * 1000 / RATED_MA)
        if index == 0x6061:
            return self.value(0x6060)
        return None

    def modes(self) -> list[int]:
        """The modes it runs: those its 0x6502 lists (without one: CSP where it has 0x607A,
        and CST)."""
        if 0x6502 in self.od:
            return [mode for mode, bit in SUPPORTED_BITS.items() if self.value(0x6502) & bit]
        return [CST, *([CSP, PP] if 0x607A in self.od else []),
                *([CSV, PV] if 0x60FF in self.od else [])]

    def torque_limit(self) -> int:
        """The torque it applies at most, per mille: its max torque and max current, those it
        has."""
        return min([self.value(index) for index in (0x6072, 0x6073) if index in self.od]
                   or [0x7FFF])

    def _on_read(self, index: int, subindex: int, od: Any) -> int | None:
        if index in self.refuses:
            raise SdoAbortedError(0x0602_0000)
        return self._live(index)

    # -- CiA 301 rules for PDO parameters, CiA 402 for the controlword ----------------------
    def _on_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        if index in self.refuses:
            raise SdoAbortedError(0x0602_0000)
        self.writes.append((index, subindex, bytes(data)))
        if index in (0x1400, 0x1800, 0x1801) and subindex == 1:
            old, new = self.value(index, 1), int.from_bytes(data, "little")
            if not (old | new) & 0x8000_0000 and (old & 0x7FF) != (new & 0x7FF):
                raise SdoAbortedError(0x0609_0030)  # invalidate before changing the COB-ID
        if index in (0x1600, 0x1A00, 0x1A01):
            comm = {0x1600: 0x1400, 0x1A00: 0x1800, 0x1A01: 0x1801}[index]
            if not self.value(comm, 1) & 0x8000_0000:
                raise SdoAbortedError(0x0601_0000)  # the mapping of a valid PDO is frozen
            value = int.from_bytes(data, "little")
            if subindex and value:
                target, sub, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
                if target not in self.od:
                    raise SdoAbortedError(0x0602_0000)
                obj = self.od[target]
                var = obj[sub] if hasattr(obj, "subindices") else obj
                if not var.pdo_mappable or len(var) != bits:
                    raise SdoAbortedError(0x0604_0041)
        if index == 0x6060 and int.from_bytes(data, "little", signed=True) not in (
                0, *self.modes()):
            raise SdoAbortedError(0x0609_0030)
        if index == 0x6040:
            self._controlword(int.from_bytes(data, "little"))

    def _controlword(self, word: int) -> None:
        previous, self.controlword = self.controlword, word
        state = self.state
        if state == "OPERATION ENABLED" and 0x6060 in self.od:
            self._mode_bit_4(word, previous)
        if word & 0x80 and not previous & 0x80:
            if state == "FAULT":
                self.state = "SWITCH ON DISABLED"
            return
        if not word & 0x02:                              # disable voltage
            self.state = "SWITCH ON DISABLED"
        elif not word & 0x04:                            # quick stop
            self.state = "QUICK STOP ACTIVE" if state == "OPERATION ENABLED" else \
                "SWITCH ON DISABLED"
        elif word & 0x0F == 0x06:                        # shutdown
            if state in ("SWITCH ON DISABLED", "SWITCHED ON", "OPERATION ENABLED"):
                self.state = "READY TO SWITCH ON"
        elif word & 0x0F == 0x07:                        # switch on (or disable operation)
            if state in ("READY TO SWITCH ON", "OPERATION ENABLED"):
                self.state = "SWITCHED ON"
        elif word & 0x0F == 0x0F and state in ("SWITCHED ON", "READY TO SWITCH ON"):
            self.state = "OPERATION ENABLED"

    # -- NMT and the cyclic path ----------------------------------------------------------
    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) == 2 and data[1] in (0, self.node_id) and data[0] == 0x01:
            self.syncs = 0

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.node.nmt.state != "OPERATIONAL":
            return
        with self.lock:
            self.syncs += 1
            for cob, payload in self.held:  # the answer it fell behind with, late
                self.network.send_message(cob, payload)
            self.held = []
            if self.latched is not None:
                self._latch_rpdo(self.latched)
            mode = self.value(0x6060) if 0x6060 in self.od else CST
            if self.state == "OPERATION ENABLED" and mode in (PP, PV, HM):
                self.current_ma = 0.0
                if mode == PP:
                    self._profile()
                elif mode == PV:
                    self._ramp()
            elif self.state == "OPERATION ENABLED":  # as a drive does: within its own limits
                limit = self.torque_limit()
                wanted = self._position_loop() if mode == CSP else \
                    self._velocity_loop() if mode == CSV else self.value(0x6071)
                torque = max(-limit, min(limit, wanted))
                self.current_ma = torque * RATED_MA / 1000
            else:
                self.current_ma = 0.0
                if self.state == "QUICK STOP ACTIVE":
                    self.velocity *= 0.5
                    if abs(self.velocity) < 1.0:
                        self.velocity = 0.0
                        self.state = "SWITCH ON DISABLED"
            if mode not in (PP, PV, HM) or self.state != "OPERATION ENABLED":
                self.velocity += GAIN_DEG_S2_PER_MA * self.current_ma * PERIOD_S
                self.position += self.velocity * PERIOD_S
            if data and self.value(0x1019):
                self.node.set_data(ECHO, 0, bytes([data[0]]))
            self._send_tpdos()

    def _mode_bit_4(self, word: int, previous: int) -> None:
        """Controlword bit 4 in PP (a new set point) and HM (start homing)."""
        mode, rising = self.value(0x6060), word & 0x10 and not previous & 0x10
        if mode == PP:
            if rising:
                raw = self.value(0x607A) * 360.0 / INCREMENTS  # on its own turn
                self.pp_target = self.position - self.position % 360.0 + raw
                self.mode_bits = 0x1000
            elif not word & 0x10:
                self.mode_bits &= ~0x1000
        elif mode == HM and rising:
            if self.value(0x6098) in (35, 37):  # home is where it stands: offset there
                offset = self.value(0x607C) * 360.0 / INCREMENTS
                self.position = offset
                self.mode_bits = 0x1400
            else:  # no switches to find: a homing error, standing
                self.mode_bits = 0x2400

    def _profile(self) -> None:
        """PP: one period of the trapezoid towards the target, position and velocity set
        as the profile says; bit 10 once within the window, standing."""
        if self.pp_target is None:
            self.velocity = 0.0
            return
        scale = 360.0 / INCREMENTS
        v_max, accel = self.value(0x6081) * scale, self.value(0x6083) * scale
        decel = self.value(0x6084) * scale
        distance = self.pp_target - self.position
        stop = (2.0 * decel * abs(distance)) ** 0.5
        wanted = min(v_max, stop) * (1 if distance >= 0 else -1)
        step = max(accel, decel) * PERIOD_S
        self.velocity += max(-step, min(step, wanted - self.velocity))
        self.position += self.velocity * PERIOD_S
        if abs(self.pp_target - self.position) <= self.value(0x6067) * scale and \
                abs(self.velocity) < step:
            self.position, self.velocity = self.pp_target, 0.0
            self.mode_bits |= 0x0400
        else:
            self.mode_bits &= ~0x0400

    def _ramp(self) -> None:
        """PV: one period of the ramp towards 0x60FF at the profile acceleration; bit 10
        once at it, bit 12 while standing."""
        scale = 360.0 / INCREMENTS
        target, step = self.value(0x60FF) * scale, self.value(0x6083) * scale * PERIOD_S
        self.velocity += max(-step, min(step, target - self.velocity))
        self.position += self.velocity * PERIOD_S
        self.mode_bits = (0x0400 if abs(target - self.velocity) < 1e-9 else 0) | \
            (0x1000 if abs(self.velocity) < 1e-9 else 0)

    def _velocity_loop(self) -> int:
        """CSV: the torque [per mille] of its velocity loop towards 0x60FF."""
        target = self.value(0x60FF) * 360.0 / INCREMENTS
        acceleration = 2 * 3.141592653589793 * 4 * LOOP_HZ * (target - self.velocity)
        return round(acceleration / GAIN_DEG_S2_PER_MA * 1000 / RATED_MA)

    def _latch_rpdo(self, data: bytes) -> None:
        """The RPDO's objects as its mapping (0x1600) says: the controlword first."""
        offset = 0
        for sub in range(1, self.value(0x1600, 0) + 1):
            entry = self.value(0x1600, sub)
            index, size = entry >> 16, (entry & 0xFF) // 8
            raw = bytes(data[offset:offset + size])
            offset += size
            if index == 0x6040:
                self._controlword(int.from_bytes(raw, "little"))
            else:
                self.node.set_data(index, (entry >> 8) & 0xFF, raw)

    def _position_loop(self) -> int:
        """CSP: the torque [per mille] of a critically damped loop towards 0x607A (its own
        turn: the target and the position compared modulo one turn)."""
        target = self.value(0x607A) * 360.0 / INCREMENTS
        error = (target - self.position + 180.0) % 360.0 - 180.0
        omega = 2 * 3.141592653589793 * LOOP_HZ
        acceleration = omega * omega * error - 2 * omega * self.velocity
        return round(acceleration / GAIN_DEG_S2_PER_MA * 1000 / RATED_MA)

    def _send_tpdos(self) -> None:
        sent = {}
        behind = self.syncs == self.behind_at
        for comm, mapping in ((0x1800, 0x1A00), (0x1801, 0x1A01)):
            cob = self.value(comm, 1)
            if cob & 0x8000_0000:
                continue
            payload = b""
            for sub in range(1, self.value(mapping, 0) + 1):
                entry = self.value(mapping, sub)
                index, bits = entry >> 16, entry & 0xFF
                live = self._live(index)
                raw = self.node.get_data(index, (entry >> 8) & 0xFF) if live is None else \
                    live.to_bytes(bits // 8, "little", signed=index != 0x6041)
                payload += raw
            if behind:
                self.held.append((cob & 0x7FF, payload))
            else:
                self.network.send_message(cob & 0x7FF, payload)
            sent[comm] = payload.hex()
        self.log.append({"sync": self.syncs, "tpdo1": sent.get(0x1800),
                         "tpdo2": sent.get(0x1801), "position_deg": self.position,
                         "state": self.state})

    def on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.node.nmt.state == "OPERATIONAL" and len(data) >= 2:
            self.latched = bytes(data)


def serve(url: str, node_id: int, behind_at: int | None = None,
          max_current_permille: int | None = None, od: ObjectDictionary | None = None
          ) -> tuple[canopen.Network, IndependentSlave]:
    """The slave on the bus at ``url`` (``INTERFACE://CHANNEL?key=value``), serving; ``od``:
    its dictionary (default: :func:`dictionary`'s)."""
    from hil.drivers.canopen.bus import open_can_bus, parse_can_url

    network = canopen.Network(open_can_bus(parse_can_url(url)))
    network.connect()
    slave = IndependentSlave(network, node_id, behind_at=behind_at,
                             max_current_permille=max_current_permille, od=od)
    network.subscribe(0x200 + node_id, slave.on_rpdo)
    return network, slave


def main(argv: list[str]) -> None:
    """``URL NODE LOG.json [--behind-at N] [--eds F.eds]``: with ``--eds``, the dictionary of
    that file."""
    url, node_id, log_path = argv[0], int(argv[1]), argv[2]
    behind_at = int(argv[argv.index("--behind-at") + 1]) if "--behind-at" in argv else None
    od = canopen.import_od(argv[argv.index("--eds") + 1], node_id) if "--eds" in argv else None
    network, slave = serve(url, node_id, behind_at, od=od)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    print("serving", flush=True)
    stop.wait()
    network.disconnect()
    with open(log_path, "w") as f:
        json.dump(slave.log, f)


if __name__ == "__main__":
    main(sys.argv[1:])
