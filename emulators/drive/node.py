"""A CiA 402 servo drive emulated on a CAN bus: NMT, SDO server, PDOs, heartbeat, EMCY, faults.

The node is transport-agnostic: frames (:data:`~drivers.can_frames.Frame`, ``(id, data)``)
come in through :meth:`DriveNode.handle_frame` (:meth:`DriveNode.handle` for a python-can
message), time-driven work (heartbeat production, watchdogs, ramp time-outs) runs in
:meth:`DriveNode.service`, and frames go out through a ``send(list_of_frames)`` callable. Two
ways to run it:

* :class:`BusRunner` - a thread that reads a python-can bus (any interface) in real time;
* :class:`LockstepDrive` - the node on a private in-process channel, pumped synchronously by
  the master after each transmission. There the node's clock is the SYNC count
  (``timebase="sync"``): the master's SYNC is the plant's clock and a run is deterministic.

(``hil emulate drive`` wires the node straight to a
:class:`~emulators.socketcand_server.SocketcandServer`, in real time.)

Cyclic path (raw frames, never the ``canopen`` PDO machinery): an RPDO is stored on reception;
on SYNC the node latches it (controlword and targets), advances the plant one communication
cycle (0x1006 / plant period steps, at least one), and sends the TPDOs whose transmission type
counter expires. SDO goes through the node's own SDO server (:mod:`emulators.drive.sdo`)
against its object access functions, so every value an SDO reads is the one the last TPDO carried.

Faults: heartbeat-consumer time-out or SYNC loss while the power stage is enabled -> EMCY
0x8130; commanded current above the trip level -> EMCY 0x2310; either starts the fault reaction
(brake to standstill, at most the quick-stop time-out) then FAULT with torque off. A fault reset
is the rising edge of controlword bit 7. Malformed frames never raise: SDO aborts with the CiA 301
code, PDO length errors and bad SYNC lengths give EMCY 0x8210 / 0x8220 / 0x8240. Leaving NMT
OPERATIONAL with the power stage on loses the cyclic commands: EMCY 0x8100 and fault.

Simplifications, on purpose: the plant moves only on SYNC, also during a quick stop or fault
reaction (without SYNC these end by their time-out, or at once when the axis already stands);
braking is the drive's velocity loop at the current limit; quick-stop options 5/6 then hold with
zero current; CSP is the drive's own position loop (P with velocity feed-forward, around a
velocity P loop); the halt bit (8) and modes other than 8 and 10 are not implemented.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import can
from canopen.objectdictionary import ODVariable
from canopen.objectdictionary.datatypes import VISIBLE_STRING

from drivers.can_frames import Frame, frames_of, from_message
from drivers.cia301 import (
    ABORT_CANNOT_MAP,
    ABORT_DEVICE_STATE,
    ABORT_LENGTH,
    ABORT_NO_OBJECT,
    ABORT_NO_SUBINDEX,
    ABORT_PDO_TOO_LONG,
    ABORT_READ_ONLY,
    ABORT_UNSUPPORTED,
    ABORT_VALUE,
    ABORT_VALUE_HIGH,
    ABORT_VALUE_LOW,
    ABORT_WRITE_ONLY,
    CYCLE_PERIOD,
    SDO_RESPONSE_BASE,
    SYNC_COB_ID,
    SYNC_COUNTER_OVERFLOW,
)
from drivers.cia402 import (
    CYCLIC_SYNCHRONOUS_POSITION,
    CYCLIC_SYNCHRONOUS_TORQUE,
    FAULT,
    FAULT_REACTION_ACTIVE,
    FAULT_RESET,
    NO_MODE,
    NOT_READY_TO_SWITCH_ON,
    OPERATION_ENABLED,
    PDO_NOT_VALID,
    QUICK_STOP_ACTIVE,
    QUICK_STOP_OPTIONS,
    QUICK_STOP_STAYS,
    QUICK_STOP_THEN_DISABLED,
    RPDOS,
    STATUSWORD_MASKS,
    SW_FOLLOWS_COMMAND,
    SW_INTERNAL_LIMIT,
    SW_REMOTE,
    SW_VOLTAGE_ENABLED,
    SW_WARNING,
    SWITCH_ON_DISABLED,
    TPDOS,
    TRANSITIONS,
    command_of,
)
from emulators.direct_bus import DirectChannel
from emulators.drive.od import OdDefaults, build_object_dictionary, iter_variables
from emulators.drive.plant import AxisPlant, Disturbance, Friction
from emulators.drive.sdo import SdoAbortError, SdoServer
from emulators.faults import Fault, FaultSchedule, for_emulator

log = logging.getLogger(__name__)

# NMT states as carried by heartbeat frames
NMT_INITIALISING, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F

MODES = (NO_MODE, CYCLIC_SYNCHRONOUS_POSITION, CYCLIC_SYNCHRONOUS_TORQUE)  # what 0x6060 accepts
# The statusword of each CiA 402 state: its bits of the profile, plus bit 9 (remote) always and
# bit 4 (voltage enabled) whenever the emulated DC link is up (every state after power-on).
STATUSWORD = {state: (value | SW_REMOTE | SW_VOLTAGE_ENABLED) if state != NOT_READY_TO_SWITCH_ON
              else value for state, (_mask, value) in STATUSWORD_MASKS.items()}
POWERED = (OPERATION_ENABLED, QUICK_STOP_ACTIVE, FAULT_REACTION_ACTIVE)

# EMCY codes (CiA 301 / 402)
EMCY_RESET = 0x0000
EMCY_OVERCURRENT = 0x2310
EMCY_SOFTWARE = 0x6100
EMCY_COMMUNICATION = 0x8100
EMCY_HEARTBEAT = 0x8130
EMCY_PDO_LENGTH = 0x8210
EMCY_PDO_TOO_LONG = 0x8220
EMCY_SYNC_LENGTH = 0x8240
ERR_REG_GENERIC, ERR_REG_CURRENT, ERR_REG_COMMUNICATION = 0x01, 0x02, 0x10
ERR_REG_VOLTAGE, ERR_REG_TEMPERATURE = 0x04, 0x08


SYNC_ECHO = 0x2004  # the counter of the SYNC the TPDOs answer (manufacturer object)
SYNC_POLL_PERIODS = 100  # SYNCs are expected until this many cycles passed without one


def error_register_bit(code: int) -> int:
    """The error register (0x1001) bit of an EMCY code's class (CiA 301, table 48)."""
    return {0x2: ERR_REG_CURRENT, 0x3: ERR_REG_VOLTAGE, 0x4: ERR_REG_TEMPERATURE,
            0x8: ERR_REG_COMMUNICATION}.get(code >> 12, ERR_REG_GENERIC)
# manufacturer byte 3 of an EMCY 0x8130: which watchdog fired
CAUSE_HEARTBEAT, CAUSE_SYNC = 0x01, 0x02

SendFn = Callable[[list[Frame]], None]


@dataclass(frozen=True)
class DriveEmulatorConfig:
    """Everything the emulated drive needs (``[emulator]`` of drive.toml, read by
    :mod:`hil.servo.config`)."""

    node_id: int = 1
    # the object dictionary's start-up values are the defaults (emulators/drive/od.py)
    rated_current_ma: int = OdDefaults.rated_current_ma
    max_torque_permille: int = OdDefaults.max_torque_permille
    current_limit_ma: float = 12_000.0
    overcurrent_trip_ma: int = OdDefaults.overcurrent_trip_ma
    increments_per_rev: int = OdDefaults.increments_per_rev
    heartbeat_ms: int = OdDefaults.heartbeat_ms
    sync_loss_timeout_ms: int = OdDefaults.sync_loss_timeout_ms
    quick_stop_option: int = OdDefaults.quick_stop_option
    quick_stop_timeout_ms: int = 3000
    standstill_deg_s: float = 2.0
    velocity_gain_ma_per_deg_s: float = 40.0
    position_gain_per_s: float = 20.0
    channel: str = "can0"
    friction: Friction = field(default_factory=Friction)
    disturbance: Disturbance = field(default_factory=Disturbance)

    def od_defaults(self) -> OdDefaults:
        return OdDefaults(
            rated_current_ma=self.rated_current_ma, max_torque_permille=self.max_torque_permille,
            increments_per_rev=self.increments_per_rev, heartbeat_ms=self.heartbeat_ms,
            sync_loss_timeout_ms=self.sync_loss_timeout_ms,
            overcurrent_trip_ma=self.overcurrent_trip_ma, quick_stop_option=self.quick_stop_option,
        )

    def make_plant(self) -> AxisPlant:
        return AxisPlant(current_limit_ma=self.current_limit_ma,
                         increments_per_rev=self.increments_per_rev,
                         friction=self.friction, disturbance=self.disturbance)


@dataclass
class _Pdo:
    """Compiled view of one PDO (rebuilt whenever its communication or mapping object changes)."""

    comm: int
    mapping: int
    transmit: bool
    cob_id: int = 0
    valid: bool = False
    trans_type: int = 1
    keys: tuple[tuple[int, int], ...] = ()
    layout: struct.Struct = field(default_factory=lambda: struct.Struct("<"))
    counter: int = 0
    length_error: bool = False


def _pdo_struct(var: ODVariable) -> struct.Struct:
    """The wire format of a variable in a PDO (fixed-size types only)."""
    data_type = var.data_type
    if data_type is None or data_type not in var.STRUCT_TYPES:
        raise SdoAbortError(ABORT_CANNOT_MAP)
    return var.STRUCT_TYPES[data_type]


def _wrap_degrees(delta_deg: float) -> float:
    """``delta_deg`` folded into [-180, 180)."""
    return (delta_deg + 180.0) % 360.0 - 180.0


class DriveNode:
    """The emulated drive. :meth:`handle`, :meth:`service` and :meth:`boot` hold ``lock``, so
    a runner may call them from different threads."""

    def __init__(
        self,
        config: DriveEmulatorConfig | None = None,
        *,
        send: SendFn,
        plant: AxisPlant | None = None,
        timebase: str = "monotonic",
        faults: Iterable[Fault] = (),
        on_fault: Callable[[str], None] | None = None,
    ) -> None:
        if timebase not in ("monotonic", "sync"):
            raise ValueError(f"timebase must be 'monotonic' or 'sync', got {timebase!r}")
        self.config = config or DriveEmulatorConfig()
        self.node_id = self.config.node_id
        self.plant = plant if plant is not None else self.config.make_plant()
        self.object_dictionary = build_object_dictionary(self.node_id, self.config.od_defaults())
        self.lock = threading.RLock()
        self._send_fn = send
        self._timebase = timebase
        self._plant_period_ns = round(self.plant.dt * 1e9)
        sdo_response_id = SDO_RESPONSE_BASE + self.node_id
        self.sdo = SdoServer(self.get_data, self.set_data,
                             lambda data: self._send([(sdo_response_id, data)]))
        self._values: dict[tuple[int, int], Any] = {}
        self._pdos = [_Pdo(p.comm, p.mapping, False) for p in RPDOS] + \
                     [_Pdo(p.comm, p.mapping, True) for p in TPDOS]
        self._pdo_by_object = {}
        for pdo in self._pdos:
            self._pdo_by_object[pdo.comm] = pdo
            self._pdo_by_object[pdo.mapping] = pdo
        self.sync_count = 0
        self._sync_time_ns = 0
        self.internal_errors = 0
        self.nmt_state = NMT_INITIALISING
        self._t0_ns = self._now()
        #: the faults played, in seconds of the node's time since it was created
        self.faults = FaultSchedule(for_emulator(faults, "drive"),
                                    lambda: (self._now() - self._t0_ns) / 1e9, on_fault)
        self._delayed: list[tuple[int, list[Frame]]] = []
        self._reset_application()

    # ---------------------------------------------------------------- life cycle and time
    @property
    def sync_time_ns(self) -> int:
        """The time its SYNCs have made: one communication cycle each."""
        return self._sync_time_ns

    @property
    def cycle_period_ns(self) -> int:
        """The communication cycle: 0x1006, or the plant's period before it is set."""
        return self._steps_per_sync * self._plant_period_ns

    def _now(self) -> int:
        return self._sync_time_ns if self._timebase == "sync" else time.monotonic_ns()

    def _reset_application(self) -> None:
        """Power-on / NMT reset node: parameters to defaults, state machine restarted."""
        for var in iter_variables(self.object_dictionary):
            self._values[(var.index, var.subindex)] = var.default
        self.state = NOT_READY_TO_SWITCH_ON
        self._controlword = 0
        self._pending_rpdo: dict[int, bytes] = {}
        self._ramp_start_ns: int | None = None
        self._limit_active = False
        self._last_target_deg: float | None = None
        self._comm_warning = False
        self.plant.extra_disturbance_ma = 0.0
        self._reset_communication_state()
        self._refresh_actuals()

    def _reset_communication_state(self) -> None:
        for pdo in self._pdos:
            self._compile_pdo(pdo)
        self._sync_cob_id = self._values[(0x1005, 0)] & 0x7FF
        self._steps_per_sync = self._steps_for_period(self._values[(0x1006, 0)])
        self._hb_next_ns: int | None = None
        self._hb_consumer_armed = False
        self._hb_last_ns = 0
        self._sync_armed = False
        self._sync_last_ns = 0

    def next_sync_ns(self, now_ns: int) -> int | None:
        """When the next SYNC is due, on the grid of the communication cycle (0x1006) from the
        last one received (the slot after, once half a period has passed without it); None
        when no cyclic SYNC is going on. A real-time runner polls the bus around that time:
        a real drive answers a SYNC within microseconds, a process woken up from a blocking
        wait may take hundreds."""
        period_ns = self._values[(0x1006, 0)] * 1000
        last = self._sync_last_ns
        if not period_ns or not last or now_ns - last > SYNC_POLL_PERIODS * period_ns:
            return None
        late = now_ns - last - period_ns - period_ns // 2
        return last + period_ns * (1 + max(0, late // period_ns + 1))

    def boot(self) -> None:
        """Power on: NOT READY TO SWITCH ON -> SWITCH ON DISABLED, boot-up message, PRE-OP."""
        with self.lock:
            self._enter_state(SWITCH_ON_DISABLED)
            self._enter_pre_operational_after_boot()

    def _enter_pre_operational_after_boot(self) -> None:
        self.nmt_state = NMT_INITIALISING
        self._send([(0x700 + self.node_id, b"\x00")])  # boot-up
        self.nmt_state = NMT_PRE_OPERATIONAL
        self._hb_next_ns = None

    # ---------------------------------------------------------------------- transport
    def _send(self, frames: list[Frame]) -> None:
        for fault in self.faults.active("silent"):
            self.faults.hit(fault)
            return
        try:
            self._send_fn(frames)
        except Exception as exc:  # a vanished client or a closed bus must not kill the node
            log.debug("drive node %d: send failed: %s", self.node_id, exc)

    # ------------------------------------------------------------------ frame dispatch
    def handle(self, msg: can.Message) -> None:
        """Process one python-can message (error, remote, 29-bit and FD frames are not for
        this node); never raises."""
        frame = from_message(msg)
        if frame is not None:
            self.handle_frame(*frame)

    def handle_frame(self, can_id: int, data: bytes) -> None:
        """Process one received 11-bit data frame; never raises."""
        with self.lock:
            if self.faults and self.faults.active("silent"):
                return  # bus-off: it hears nothing either
            try:
                self._dispatch(can_id, data)
            except Exception:  # a bug must not take the drive down: report it as an EMCY
                self.internal_errors += 1
                log.exception("drive node %d: internal error on frame 0x%03X %s",
                              self.node_id, can_id, data.hex())
                self._emcy(EMCY_SOFTWARE, ERR_REG_GENERIC)

    def _dispatch(self, can_id: int, data: bytes) -> None:
        n = self.node_id
        if can_id == 0x000:
            self._on_nmt(data)
        elif 0x700 <= can_id <= 0x77F:
            self._on_heartbeat(can_id - 0x700, data)
        elif self.nmt_state == NMT_STOPPED:
            return  # only NMT and heartbeats are served in STOPPED
        elif can_id == self._sync_cob_id:
            self._on_sync(data)
        elif can_id == 0x600 + n:
            self.sdo.handle(data)
        else:
            for pdo in self._pdos:
                if not pdo.transmit and pdo.valid and pdo.cob_id == can_id:
                    self._on_rpdo(pdo, data)
                    break

    # ------------------------------------------------------------------------------ NMT
    def _on_nmt(self, data: bytes) -> None:
        if len(data) != 2 or data[1] not in (0, self.node_id):
            return
        command = data[0]
        if command == 0x01:
            self._set_nmt(NMT_OPERATIONAL)
        elif command == 0x02:
            self._set_nmt(NMT_STOPPED)
        elif command == 0x80:
            self._set_nmt(NMT_PRE_OPERATIONAL)
        elif command == 0x81:  # reset node: application and communication
            self._reset_application()
            self._enter_state(SWITCH_ON_DISABLED)
            self._enter_pre_operational_after_boot()
        elif command == 0x82:  # reset communication
            self._leave_operational_check()
            for var in iter_variables(self.object_dictionary):
                if var.index < 0x2000:
                    self._values[(var.index, var.subindex)] = var.default
            self._reset_communication_state()
            self._refresh_actuals()
            self._enter_pre_operational_after_boot()

    def _set_nmt(self, state: int) -> None:
        if state == self.nmt_state:
            return
        if self.nmt_state == NMT_OPERATIONAL:
            self._leave_operational_check()
        self.nmt_state = state
        if state == NMT_OPERATIONAL:
            self._pending_rpdo.clear()
            for pdo in self._pdos:
                pdo.counter = 0

    def _leave_operational_check(self) -> None:
        """Leaving OPERATIONAL with the power stage on loses the cyclic commands: fault."""
        if self.nmt_state == NMT_OPERATIONAL and self.state in (OPERATION_ENABLED,
                                                                QUICK_STOP_ACTIVE):
            self._fault(EMCY_COMMUNICATION, ERR_REG_COMMUNICATION)

    # ------------------------------------------------------------------------- heartbeat
    def _on_heartbeat(self, producer: int, data: bytes) -> None:
        consumer = self._values[(0x1016, 1)]
        watched, timeout_ms = (consumer >> 16) & 0x7F, consumer & 0xFFFF
        if len(data) < 1 or producer != watched or not watched or not timeout_ms:
            return
        self._hb_last_ns = self._now()
        self._hb_consumer_armed = True
        if self._comm_warning and self.state != FAULT:  # the lost master is back
            self._comm_warning = False
            self._values[(0x1001, 0)] &= ~(ERR_REG_COMMUNICATION | ERR_REG_GENERIC)
            self._emcy(EMCY_RESET, 0)

    # ------------------------------------------------------------------------------ SDO
    def _find_object(self, index: int, subindex: int) -> ODVariable:
        if index not in self.object_dictionary:
            raise SdoAbortError(ABORT_NO_OBJECT)
        obj = self.object_dictionary[index]
        if isinstance(obj, ODVariable):
            if subindex != 0:
                raise SdoAbortError(ABORT_NO_SUBINDEX)
            return obj
        if subindex not in obj.subindices:
            raise SdoAbortError(ABORT_NO_SUBINDEX)
        return obj.subindices[subindex]

    def get_data(self, index: int, subindex: int) -> bytes:
        """SDO upload (the SDO server's read)."""
        var = self._find_object(index, subindex)
        if not var.readable:
            raise SdoAbortError(ABORT_WRITE_ONLY)
        return var.encode_raw(self._values[(index, subindex)])

    def set_data(self, index: int, subindex: int, data: bytes) -> None:
        """SDO download (the SDO server's write): type, range and state checks."""
        var = self._find_object(index, subindex)
        if not var.writable:
            raise SdoAbortError(ABORT_READ_ONLY)
        if var.data_type == VISIBLE_STRING:
            raise SdoAbortError(ABORT_READ_ONLY)
        if len(data) * 8 != len(var):
            raise SdoAbortError(ABORT_LENGTH)
        value = var.decode_raw(bytes(data))
        if not isinstance(value, int):  # the emulator's writable objects are integers
            raise SdoAbortError(ABORT_READ_ONLY)
        if var.min is not None and value < var.min:
            raise SdoAbortError(ABORT_VALUE_LOW)
        if var.max is not None and value > var.max:
            raise SdoAbortError(ABORT_VALUE_HIGH)
        self._write(index, subindex, value)

    # ------------------------------------------------------------- object write effects
    def _write(self, index: int, subindex: int, value: int) -> None:
        """Validate and apply one write (SDO); raises SdoAbortError with the CiA code."""
        key = (index, subindex)
        if index in self._pdo_by_object:
            self._write_pdo_parameter(self._pdo_by_object[index], index, subindex, value)
            return
        if index == 0x1005:
            if value & 0x6000_0000 or value & 0x7FF == 0:  # we do not produce SYNC, 11-bit only
                raise SdoAbortError(ABORT_VALUE)
            self._values[key] = value
            self._sync_cob_id = value & 0x7FF
        elif index == SYNC_COUNTER_OVERFLOW:
            if self._values[(CYCLE_PERIOD, 0)] != 0 or value == 1:
                raise SdoAbortError(ABORT_DEVICE_STATE if value != 1 else ABORT_VALUE)
            self._values[key] = value
        elif index == 0x1006:
            steps = self._steps_for_period(value)
            self._values[key] = value
            self._steps_per_sync = steps
        elif index == 0x1016:
            if value & 0xFF80_0000 or (value >> 16) == self.node_id:
                raise SdoAbortError(ABORT_VALUE)
            self._values[key] = value
            self._hb_consumer_armed = False
        elif index == 0x1017:
            self._values[key] = value
            self._hb_next_ns = None
        elif index == 0x605A:
            if value not in QUICK_STOP_OPTIONS:
                raise SdoAbortError(ABORT_VALUE)
            self._values[key] = value
        elif index == 0x6060:
            if value not in MODES:
                raise SdoAbortError(ABORT_VALUE)
            self._values[key] = value
            self._values[(0x6061, 0)] = value
        elif index == 0x6040:
            self._apply_controlword(value)
        elif index == 0x2003:
            self._values[key] = value
            self.plant.extra_disturbance_ma = float(value)
        else:
            self._values[key] = value

    def _steps_for_period(self, period_us: int) -> int:
        """Plant steps per SYNC for a communication cycle period (0 = not set: one step); a
        period that is no multiple of the plant's is refused (SdoAbortError)."""
        if period_us == 0:
            return 1
        period_ns = period_us * 1000
        if period_ns % self._plant_period_ns:
            raise SdoAbortError(ABORT_VALUE)
        return period_ns // self._plant_period_ns

    # ------------------------------------------------------------------------------ PDOs
    def _write_pdo_parameter(self, pdo: _Pdo, index: int, subindex: int, value: int) -> None:
        key = (index, subindex)
        if index == pdo.comm:
            if subindex == 1:
                if value & 0x2000_0000 or value & 0x7FF == 0:
                    raise SdoAbortError(ABORT_VALUE)  # 29-bit ids are not supported here
                old = self._values[key]
                both_valid = not (old | value) & PDO_NOT_VALID
                if both_valid and (old & 0x7FF) != (value & 0x7FF):
                    raise SdoAbortError(ABORT_VALUE)  # invalidate before changing the id
            elif subindex == 2:
                allowed = range(1, 241) if pdo.transmit else [*range(241), 254, 255]
                if value not in allowed:
                    raise SdoAbortError(ABORT_VALUE)
            self._values[key] = value
        else:
            if not self._values[(pdo.comm, 1)] & PDO_NOT_VALID:
                raise SdoAbortError(ABORT_UNSUPPORTED)  # mapping of a valid PDO is frozen
            if subindex == 0:
                self._check_mapping(pdo, [self._values[(index, s)] for s in range(1, value + 1)])
            elif self._values[(index, 0)] != 0:
                raise SdoAbortError(ABORT_UNSUPPORTED)  # disable the mapping first
            elif value:  # 0 clears an unused entry
                self._check_mapping(pdo, [value])
            self._values[key] = value
        self._compile_pdo(pdo)

    def _check_mapping(self, pdo: _Pdo, entries: list[int]) -> None:
        bits = 0
        for entry in entries:
            index, subindex, size = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
            try:
                var = self._find_object(index, subindex)
            except SdoAbortError:
                raise SdoAbortError(ABORT_NO_OBJECT) from None
            usable = var.readable if pdo.transmit else var.writable
            if not var.pdo_mappable or not usable or size != len(var):
                raise SdoAbortError(ABORT_CANNOT_MAP)
            bits += size
        if bits > 64:
            raise SdoAbortError(ABORT_PDO_TOO_LONG)

    def _compile_pdo(self, pdo: _Pdo) -> None:
        cob = self._values[(pdo.comm, 1)]
        pdo.cob_id = cob & 0x7FF
        pdo.valid = not cob & PDO_NOT_VALID
        pdo.trans_type = self._values[(pdo.comm, 2)]
        keys, fmt = [], "<"
        for sub in range(1, self._values[(pdo.mapping, 0)] + 1):
            entry = self._values[(pdo.mapping, sub)]
            index, subindex = entry >> 16, (entry >> 8) & 0xFF
            var = self._find_object(index, subindex)
            keys.append((index, subindex))
            fmt += _pdo_struct(var).format.lstrip("<")
        pdo.keys, pdo.layout = tuple(keys), struct.Struct(fmt)

    def _on_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        if self.nmt_state != NMT_OPERATIONAL:
            return
        size = pdo.layout.size
        if len(data) < size:
            if not pdo.length_error:
                pdo.length_error = True
                self._emcy(EMCY_PDO_LENGTH, ERR_REG_COMMUNICATION, raise_register=False)
            return
        if len(data) > size and not pdo.length_error:
            pdo.length_error = True
            self._emcy(EMCY_PDO_TOO_LONG, ERR_REG_COMMUNICATION, raise_register=False)
        elif len(data) == size:
            pdo.length_error = False
        if pdo.trans_type <= 240:
            self._pending_rpdo[pdo.comm] = data[:size]  # latched on the next SYNC
        else:
            self._apply_rpdo(pdo, data[:size])

    def _apply_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        controlword = None
        for key, value in zip(pdo.keys, pdo.layout.unpack(data), strict=True):
            if key == (0x6040, 0):
                controlword = value  # applied after the targets of the same PDO
            elif key == (0x6060, 0) and value not in MODES:
                continue  # invalid mode in a PDO: ignored, the display keeps the active mode
            else:
                try:
                    self._write(key[0], key[1], value)
                except SdoAbortError:
                    continue  # a value the object refuses: ignored like an invalid mode
        if controlword is not None:
            self._apply_controlword(controlword)

    def _send_tpdos(self) -> None:
        frames = []
        for pdo in self._pdos:
            if not pdo.transmit or not pdo.valid:
                continue
            pdo.counter += 1
            if pdo.counter >= pdo.trans_type:
                pdo.counter = 0
                values = [self._values[key] for key in pdo.keys]
                frames.append((pdo.cob_id, pdo.layout.pack(*values)))
        if frames and self.faults:
            for fault in self.faults.active("drop_tpdo"):
                if self.faults.hit(fault) % fault.params["every"] == 0:
                    return
            for fault in self.faults.active("delay_tpdo"):
                self.faults.hit(fault)
                self._delayed.append((self._now() + round(fault.params["ms"] * 1e6), frames))
                return
        if frames and self._delayed:  # one output queue: held answers go out first
            self._delayed.append((self._delayed[-1][0], frames))
        elif frames:
            self._send(frames)

    # ----------------------------------------------------------------------------- SYNC
    def _on_sync(self, data: bytes) -> None:
        if len(data) > 1:
            self._emcy(EMCY_SYNC_LENGTH, ERR_REG_COMMUNICATION, raise_register=False)
            return
        if data and self._values[(SYNC_COUNTER_OVERFLOW, 0)]:  # the SYNC counter is on
            self._values[(SYNC_ECHO, 0)] = data[0]
        operational = self.nmt_state == NMT_OPERATIONAL
        if operational and self._pending_rpdo:
            for pdo in self._pdos:
                latched = self._pending_rpdo.pop(pdo.comm, None)
                if latched is not None:
                    self._apply_rpdo(pdo, latched)
        self._advance_plant()
        self.sync_count += 1
        self._sync_time_ns += self._steps_per_sync * self._plant_period_ns
        self._sync_last_ns = self._now()
        self._sync_armed = operational and self.state in (OPERATION_ENABLED, QUICK_STOP_ACTIVE)
        if operational:
            self._send_tpdos()

    def _advance_plant(self) -> None:
        current, self._limit_active = self._motor_current()
        self.plant.step(current, self._steps_per_sync)
        if self._ramp_start_ns is not None and abs(self.plant.velocity_deg_s) < \
                self.config.standstill_deg_s:
            self._ramp_finished()
        self._refresh_actuals()

    def _current_limit_ma(self) -> float:
        rated = self._values[(0x6075, 0)]
        return min(self._values[(0x6072, 0)] * rated / 1000.0, self.plant.current_limit_ma)

    def _motor_current(self) -> tuple[float, bool]:
        """The current the drive applies this cycle and whether it had to limit it."""
        limit = self._current_limit_ma()
        if self.state == OPERATION_ENABLED:
            mode = self._values[(0x6061, 0)]
            if mode == CYCLIC_SYNCHRONOUS_TORQUE:
                wanted = self._values[(0x6071, 0)] * self._values[(0x6075, 0)] / 1000.0
                if abs(wanted) > self._values[(0x2002, 0)]:
                    self._fault(EMCY_OVERCURRENT, ERR_REG_CURRENT)
                    return self._motor_current()  # the fault reaction's current
            elif mode == CYCLIC_SYNCHRONOUS_POSITION:
                wanted = self._position_loop()
            else:
                return 0.0, False
        elif self._ramp_start_ns is not None:
            wanted = self._brake_current(limit)
        else:
            return 0.0, False
        limited = min(max(wanted, -limit), limit)
        return limited, limited != wanted

    def _brake_current(self, limit: float) -> float:
        wanted = -self.config.velocity_gain_ma_per_deg_s * self.plant.velocity_deg_s
        return min(max(wanted, -limit), limit)

    def _position_loop(self) -> float:
        """CSP: position P loop with velocity feed-forward (the target's change per cycle)
        around a velocity P loop: the emulated drive's own servo."""
        target_deg = self._values[(0x607A, 0)] * 360.0 / self.plant.increments_per_rev
        previous, self._last_target_deg = self._last_target_deg, target_deg
        cycle_s = self._steps_per_sync * self.plant.dt
        feed_forward = 0.0 if previous is None else _wrap_degrees(target_deg - previous) / cycle_s
        error = _wrap_degrees(target_deg - self.plant.position_deg)
        velocity_ref = self.config.position_gain_per_s * error + feed_forward
        return self.config.velocity_gain_ma_per_deg_s * (velocity_ref - self.plant.velocity_deg_s)

    def _refresh_actuals(self) -> None:
        values, plant = self._values, self.plant
        values[(0x6064, 0)] = plant.position_increments()
        values[(0x606C, 0)] = plant.velocity_increments_s()
        torque = round(plant.applied_current_ma * 1000.0 / values[(0x6075, 0)])
        values[(0x6077, 0)] = max(-32768, min(32767, torque))
        values[(0x6041, 0)] = self.statusword

    # --------------------------------------------------------------- CiA 402 state machine
    @property
    def statusword(self) -> int:
        word = STATUSWORD[self.state]
        if self.state == OPERATION_ENABLED:
            word |= SW_FOLLOWS_COMMAND
            if self._limit_active:
                word |= SW_INTERNAL_LIMIT
        if self._comm_warning and self.state not in (FAULT, FAULT_REACTION_ACTIVE):
            word |= SW_WARNING
        return word

    def _enter_state(self, state: str) -> None:
        if state == self.state:
            return
        log.debug("drive node %d: %s -> %s", self.node_id, self.state, state)
        self.state = state
        if state not in (QUICK_STOP_ACTIVE, FAULT_REACTION_ACTIVE):
            self._ramp_start_ns = None
        self._last_target_deg = None  # CSP feed-forward starts afresh
        if state not in POWERED:
            self._sync_armed = False
            self.plant.applied_current_ma = 0.0
        self._refresh_actuals()

    def _apply_controlword(self, cw: int) -> None:
        """One controlword write (SDO) or latch (RPDO on SYNC): the transitions its command
        makes from the current state (:data:`drivers.cia402.TRANSITIONS`)."""
        for fault in self.faults.active("ignore_controlword"):
            self.faults.hit(fault)
            return
        previous, self._controlword = self._controlword, cw
        self._values[(0x6040, 0)] = cw
        command = command_of(cw, previous)
        if command is None:
            return
        for number, state in TRANSITIONS.get((self.state, command), ()):
            if number == 16 and self._values[(0x605A, 0)] not in QUICK_STOP_STAYS:
                return
            if command == FAULT_RESET:
                self._clear_errors()
            if state == QUICK_STOP_ACTIVE:
                self._start_quick_stop()
            else:
                self._enter_state(state)

    def _start_quick_stop(self) -> None:
        self._enter_state(QUICK_STOP_ACTIVE)
        if self._values[(0x605A, 0)] == 0:
            self._enter_state(SWITCH_ON_DISABLED)  # option 0: disable drive function at once
            return
        self._ramp_start_ns = self._now()
        if abs(self.plant.velocity_deg_s) < self.config.standstill_deg_s:
            self._ramp_finished()

    def _ramp_finished(self) -> None:
        """Standstill reached (or the ramp timed out): torque off where the option says so."""
        self._ramp_start_ns = None
        if self.state == FAULT_REACTION_ACTIVE:
            self._enter_state(FAULT)  # 14
        elif self.state == QUICK_STOP_ACTIVE and \
                self._values[(0x605A, 0)] in QUICK_STOP_THEN_DISABLED:
            self._enter_state(SWITCH_ON_DISABLED)  # 12
        self.plant.applied_current_ma = 0.0

    def _fault(self, code: int, register: int, cause: int = 0) -> None:
        """A fault: EMCY, then the fault reaction (13), then FAULT (14) at standstill."""
        if self.state in (FAULT, FAULT_REACTION_ACTIVE):
            return
        self._values[(0x603F, 0)] = code
        self._emcy(code, register, bytes([cause]) if cause else b"")
        self._enter_state(FAULT_REACTION_ACTIVE)
        self._ramp_start_ns = self._now()
        if abs(self.plant.velocity_deg_s) < self.config.standstill_deg_s:
            self._ramp_finished()

    def _clear_errors(self) -> None:
        self._values[(0x603F, 0)] = 0
        self._values[(0x1001, 0)] = 0
        self._comm_warning = False
        self._emcy(EMCY_RESET, 0)

    # ----------------------------------------------------------------------------- EMCY
    def _emcy(self, code: int, register: int, manufacturer: bytes = b"",
              raise_register: bool = True) -> None:
        if raise_register and register:
            self._values[(0x1001, 0)] |= register | ERR_REG_GENERIC
        if self.nmt_state not in (NMT_PRE_OPERATIONAL, NMT_OPERATIONAL):
            return  # EMCY is not allowed in STOPPED
        payload = struct.pack("<HB", code, self._values[(0x1001, 0)]) + manufacturer.ljust(5, b"\0")
        self._send([(0x80 + self.node_id, payload[:8])])

    # -------------------------------------------------------------------- time service
    def service(self) -> None:
        """Time-driven work: heartbeat production, watchdogs, ramp time-outs. Never raises."""
        with self.lock:
            try:
                self._service(self._now())
            except Exception:
                self.internal_errors += 1
                log.exception("drive node %d: internal error in service", self.node_id)

    def _service(self, now: int) -> None:
        if self.nmt_state == NMT_INITIALISING:
            return
        if self.faults:
            self._service_faults(now)
        period_ms = self._values[(0x1017, 0)]
        if period_ms and (self._hb_next_ns is None or now >= self._hb_next_ns):
            if not self.faults.active("no_heartbeat"):
                self._send([(0x700 + self.node_id, bytes([self.nmt_state]))])
            late = self._hb_next_ns is None or now - self._hb_next_ns > period_ms * 1_000_000
            base = now if late else self._hb_next_ns
            self._hb_next_ns = base + period_ms * 1_000_000
        consumer_ms = self._values[(0x1016, 1)] & 0xFFFF
        if self._hb_consumer_armed and now - self._hb_last_ns > consumer_ms * 1_000_000:
            self._hb_consumer_armed = False
            self._communication_lost(CAUSE_HEARTBEAT)
        sync_ms = self._values[(0x2001, 0)]
        if self._sync_armed and sync_ms and now - self._sync_last_ns > sync_ms * 1_000_000:
            self._sync_armed = False
            self._communication_lost(CAUSE_SYNC)
        if self._ramp_start_ns is not None and \
                now - self._ramp_start_ns > self.config.quick_stop_timeout_ms * 1_000_000:
            self._ramp_finished()

    def _service_faults(self, now: int) -> None:
        """Delayed TPDOs that are due; an ``emcy`` fault raises its EMCY and FAULT once."""
        while self._delayed and self._delayed[0][0] <= now:
            self._send(self._delayed.pop(0)[1])
        for fault in self.faults.active("emcy"):
            if self.faults.hit(fault) == 1:
                self._fault(fault.params["code"], error_register_bit(fault.params["code"]))

    def _communication_lost(self, cause: int) -> None:
        if self.state in (OPERATION_ENABLED, QUICK_STOP_ACTIVE):
            self._fault(EMCY_HEARTBEAT, ERR_REG_COMMUNICATION, cause)
        else:  # no torque to take away: report it and flag a warning in the statusword
            self._comm_warning = True
            self._emcy(EMCY_HEARTBEAT, ERR_REG_COMMUNICATION, bytes([cause]))
            self._values[(0x6041, 0)] = self.statusword


def bus_sender(bus: can.BusABC) -> SendFn:
    """A node ``send`` function writing to a python-can bus."""
    return frames_of(bus).send_frames


class BusRunner:
    """Runs a :class:`DriveNode` on a python-can bus in a background thread (real time)."""

    def __init__(self, node: DriveNode, bus: can.BusABC, service_period_s: float = 0.001) -> None:
        self.node, self.bus = node, bus
        self._period = service_period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"drive-node-{node.node_id}",
                                        daemon=True)

    def start(self) -> BusRunner:
        self.node.boot()
        self._thread.start()
        return self

    def _run(self) -> None:
        next_service = time.monotonic()
        recv = frames_of(self.bus).recv_frame
        while not self._stop.is_set():
            try:
                frame = recv(max(0.0, next_service - time.monotonic()))
            except can.CanError:
                break  # the bus is gone
            if frame is not None:
                self.node.handle_frame(*frame)
            if time.monotonic() >= next_service:
                self.node.service()
                next_service = time.monotonic() + self._period

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)

    def __enter__(self) -> BusRunner:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()


class LockstepDrive:
    """An emulated drive on a private in-process channel (:mod:`emulators.direct_bus`), run
    synchronously: every transmission on :attr:`master_bus` hands the pending frames to the
    node and runs its time service before the send returns (no threads).

    The node's clock is its SYNC count, so the run is deterministic and as fast as the CPU
    allows. The drive is also the master's clock in lockstep (:meth:`time_ns`, :meth:`sleep`):
    time passes for it when SYNCs come, so a master waiting for a state lets time pass by
    sending SYNCs.
    """

    def __init__(self, config: DriveEmulatorConfig | None = None,
                 plant: AxisPlant | None = None) -> None:
        self.channel = DirectChannel(f"hil-drive-{uuid.uuid4().hex}")
        self._node_bus = self.channel.attach()
        self.master_bus = self.channel.attach(on_send=self.pump)
        self._time_bus = self.channel.attach(on_send=self.pump)
        self.node = DriveNode(config, send=self._node_bus.send_frames, plant=plant,
                              timebase="sync")
        self.node.boot()

    def attach_bus(self) -> can.BusABC:
        """One more bus on the same channel (an observer or a second master)."""
        return self.channel.attach()

    def pump(self) -> None:
        """Deliver every frame waiting for the node, then run its time service."""
        recv, handle = self._node_bus.recv_frame, self.node.handle_frame
        while (frame := recv()) is not None:
            handle(*frame)
        self.node.service()

    def time_ns(self) -> int:
        """The drive's time: its SYNCs so far, one communication cycle each."""
        return self.node.sync_time_ns

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` of the drive's time pass: one SYNC per communication cycle."""
        period_ns = self.node.cycle_period_ns
        for _ in range(max(1, math.ceil(seconds * 1e9 / period_ns))):
            self._time_bus.send_frames([(SYNC_COB_ID, b"")])

    def close(self) -> None:
        for bus in (self._node_bus, self.master_bus, self._time_bus):
            bus.shutdown()
