"""CiA 402 master over python-can: configure, enable, cyclic exchange, watchdogs, safe stop.

One :class:`CanDriveMaster` drives one servo drive. Everything happens in the caller's thread
(no ``Notifier``, whose thread dies silently when a listener raises): SDO requests wait for their
answer, and each cycle sends RPDO1 then SYNC and reads TPDO1 (statusword, position) and TPDO2
(velocity, torque) back. Use from a loop task either in one call per tick::

    feedback = master.exchange(current_mA)          # RPDO + SYNC, then wait for the TPDOs

or split over two ticks, which lets the TPDOs travel while the loop sleeps (real time)::

    feedback = master.receive_feedback()            # in Task.read: the previous SYNC's TPDOs
    master.send_command(current_mA)                 # in Task.write: RPDO + SYNC

Either way ``feedback`` reflects the command of the previous cycle applied for one period
(``x(k+1) = A x(k) + B u(k)``). Safety lives here, not in the controller: commands are clamped
to ``current_limit_mA``; no TPDO for ``stale_cycles`` cycles, a send error or a drive reboot ->
link lost; a FAULT or any state other than OPERATION ENABLED -> error. Each of these puts the
drive into its safe state (quick stop, then disable voltage), emits an event and latches: every
later cyclic call raises until :meth:`CanDriveMaster.reset_fault` recovers explicitly.
EMCY frames become ``drive.emcy`` events through ``on_event`` (``Session.event`` fits).

The master is a :class:`hil.core.types.Device`: :meth:`~CanDriveMaster.open` (SDO, voltage
disabled), :meth:`~CanDriveMaster.configure` (mode, PDO map, heartbeats, limits),
:meth:`~CanDriveMaster.enable` (OPERATION ENABLED), :meth:`~CanDriveMaster.safe_state`,
:meth:`~CanDriveMaster.close`. :func:`open_socketcand` and :func:`open_interface` build one for
``socketcand://HOST:PORT[/CHANNEL]`` and any python-can ``INTERFACE://CHANNEL``; the CiA 402
vocabulary (states, controlwords, PDO map) is :mod:`drivers.cia402`.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

import can
from canopen.sdo import SdoAbortedError

from drivers.can_bus_time import BusBudget, cia402_cyclic_frames, cycle_budget
from drivers.can_frames import Frame, frames_of
from drivers.cia402 import (
    CONTROLWORD,
    CW_DISABLE_VOLTAGE,
    CW_ENABLE_OPERATION,
    CW_FAULT_RESET,
    CW_QUICK_STOP,
    CYCLIC_SYNCHRONOUS_POSITION,
    CYCLIC_SYNCHRONOUS_TORQUE,
    FAULT,
    FAULT_REACTION_ACTIVE,
    MODES,
    NOT_READY_TO_SWITCH_ON,
    OPERATION_ENABLED,
    PDO_NOT_VALID,
    QUICK_STOP_ACTIVE,
    STATUSWORD,
    SUPPORTED_MODE_BITS,
    SWITCH_ON_DISABLED,
    TPDO1,
    TPDO2,
    TPDOS,
    PdoMap,
    enable_steps,
    rpdo1_for,
    state_of,
)
from drivers.socketcand_bus import SocketcandBus
from hil.core.errors import ConfigError, HilError
from hil.core.types import Device, EventSink, LinkWatchdog, no_event

NMT_START, NMT_PRE_OPERATIONAL = 0x01, 0x80
POLL_WAIT_MAX_NS = 2_000_000  # TPDO waits up to this long poll the bus instead of blocking
CST, CSP = CYCLIC_SYNCHRONOUS_TORQUE, CYCLIC_SYNCHRONOUS_POSITION
ENABLE_STEPS = enable_steps()  # (controlword, state it leads to) from SWITCH ON DISABLED
EMCY_NAMES = {
    0x0000: "error reset", 0x1000: "generic error", 0x2310: "continuous over-current",
    0x3210: "DC link over-voltage", 0x4310: "drive over-temperature",
    0x6100: "internal software error", 0x8100: "communication error",
    0x8110: "CAN overrun", 0x8120: "CAN error passive", 0x8130: "heartbeat or life guard error",
    0x8140: "recovered from bus-off", 0x8210: "PDO not processed (length error)",
    0x8220: "PDO length exceeded", 0x8240: "unexpected SYNC data length",
}

# python-can logs warnings (e.g. socketcand's "Got incomplete message => waiting for more
# data") that Python's last-resort handler would print on stderr; the driver reports what
# matters as events and errors. A user's own logging configuration still sees them.
logging.getLogger("can").addHandler(logging.NullHandler())


class DriveError(HilError):
    """The drive or the link to it is not in a state to be commanded."""


class DriveFaultError(DriveError):
    """The drive reports FAULT; ``emcy_code`` is its last error code (0 if unknown)."""

    def __init__(self, message: str, emcy_code: int = 0) -> None:
        super().__init__(message)
        self.emcy_code = emcy_code


class DriveLinkLostError(DriveError):
    """No answer from the drive (TPDO watchdog, SDO time-out, bus error, reboot)."""


class DriveStateError(DriveError):
    """The CiA 402 state machine is not where it should be (stuck, or left OPERATION ENABLED)."""


class SdoAbortError(DriveError):
    """The drive refused an SDO request; ``code`` is the CiA 301 abort code."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


# ------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class DriveMasterConfig:
    """The master's settings (``[master]`` and ``[bus]`` of drive.toml, read by
    :mod:`hil.servo.config`)."""

    node_id: int = 1
    mode: str = "cst"
    cycle_period_s: float = 500e-6
    bitrate: int = 1_000_000
    channel: str = "can0"
    current_limit_ma: float = 1000.0
    heartbeat_id: int = 127
    heartbeat_period_ms: int = 50
    heartbeat_timeout_ms: int = 300
    drive_heartbeat_ms: int = 100
    stale_cycles: int = 20
    rx_timeout_s: float = 400e-6
    sdo_timeout_s: float = 1.0
    state_timeout_s: float = 2.0
    quick_stop_option: int = 2
    quick_stop_timeout_s: float = 3.0
    standstill_deg_s: float = 2.0


# ------------------------------------------------------------------------------ feedback
@dataclass(frozen=True, slots=True)
class Feedback:
    """What the drive reported for one cycle (``fresh`` False: the TPDOs did not arrive in
    time and the values are the previous cycle's)."""

    position_deg: float       # multi-turn, unwrapped by the master
    velocity_deg_s: float
    current_ma: float         # torque actual, as motor current
    statusword: int
    position_increments: int  # as on the wire: modulo one revolution
    cycle: int                # SYNC count of this master
    t_ns: int                 # master time base on reception (cycle * period, or monotonic)
    fresh: bool
    rtt_us: float             # SYNC sent -> both TPDOs received (wall clock)
    command_ma: float         # the current the cycle commanded (after the clamp)

    @property
    def state(self) -> str:
        return state_of(self.statusword)


@dataclass
class LinkStats:
    """Counters of the cyclic link since the master was built."""

    cycles: int = 0
    fresh: int = 0
    stale: int = 0
    longest_stale_run: int = 0
    late_frames: int = 0
    malformed_frames: int = 0
    clamped_commands: int = 0
    emcy: int = 0


# -------------------------------------------------------------------------------- master
class CanDriveMaster(Device):
    """CiA 402 master for one drive on a python-can bus (a :class:`~hil.core.types.Device`).

    :meth:`start` (:meth:`open`, :meth:`configure`, :meth:`enable`) comes first. ``url`` names
    the drive in events and errors (default: the bus's channel info)."""

    def __init__(
        self,
        bus: can.BusABC,
        config: DriveMasterConfig | None = None,
        *,
        on_event: EventSink = no_event,
        timebase: str = "monotonic",
        pump: Callable[[], None] | None = None,
        bus_factory: Callable[[], can.BusABC] | None = None,
        closers: tuple[Callable[[], None], ...] = (),
        url: str | None = None,
    ) -> None:
        if timebase not in ("monotonic", "cycles"):
            raise ValueError(f"timebase must be 'monotonic' or 'cycles', got {timebase!r}")
        self.config = config or DriveMasterConfig()
        self._use_bus(bus)
        self._url = url if url is not None else str(bus.channel_info)
        self.node_id = self.config.node_id
        self.mode = MODES[self.config.mode]
        self._on_event = on_event
        self._timebase = timebase
        self._pump = pump
        self._bus_factory = bus_factory
        self._closers = closers
        self._period_ns = round(self.config.cycle_period_s * 1e9)
        #: the drive's heartbeat is missed after 3 periods (CiA 301 consumers allow 1.5-3)
        self._heartbeat_timeout_ns = 3 * self.config.drive_heartbeat_ms * 1_000_000
        self._rx_timeout_ns = 0 if pump is not None else round(self.config.rx_timeout_s * 1e9)
        n = self.node_id
        self._rpdo1_map = rpdo1_for(self.mode)
        self._tpdo1, self._tpdo2 = TPDO1.cob_id(n), TPDO2.cob_id(n)
        self._rpdo1 = self._rpdo1_map.cob_id(n)
        self._rpdo_layout = struct.Struct("<Hh" if self.mode == CST else "<Hi")
        self._sync: Frame = (0x80, b"")
        self._heartbeat: Frame = (0x700 + self.config.heartbeat_id, b"\x05")
        self.stats = LinkStats()
        self.budget = self._bus_budget()
        self.rated_current_ma = 1000.0
        self.increments_per_rev = 1 << 20
        self.last_emcy_code = 0
        self.feedback: Feedback | None = None
        self._cycle = 0
        self.watchdog = LinkWatchdog(self.config.stale_cycles, "cycles without a TPDO")
        self._awaiting = False
        self._got = 0
        self._rx_statusword = self._rx_position = self._rx_velocity = self._rx_torque = 0
        self._sent_ns = 0
        self._command_ma = 0.0
        self._next_heartbeat_ns: int | None = None
        self._turns = 0
        self._last_raw: int | None = None
        self._sdo_inbox: list[bytes] = []
        self._rebooted = False
        self._drive_heartbeat_ns = 0  # the drive's last heartbeat (master time base)
        self._enabled = False
        self._latched: DriveError | None = None
        self._closed = False

    @property
    def url(self) -> str:
        return self._url

    @property
    def link_up(self) -> bool:
        """False from a lost link (no TPDO, send error, reboot) until :meth:`reset_fault`."""
        return not self.watchdog.lost and not isinstance(self._latched, DriveLinkLostError)

    # ----------------------------------------------------------------------- plumbing
    def _use_bus(self, bus: can.BusABC) -> None:
        """Talk through ``bus`` from now on, in :data:`~drivers.can_frames.Frame` tuples: a
        bus that carries them natively (SocketcandBus: a cycle's frames in one TCP write; the
        lockstep DirectBus) without a :class:`can.Message` per frame."""
        self.bus = bus
        frames = frames_of(bus)
        self._send_frames, self._recv_frame = frames.send_frames, frames.recv_frame

    def _event(self, kind: str, message: str, level: str = "info", **data: Any) -> None:
        self._on_event(kind, message, level=level, source=f"drive{self.node_id}", **data)

    def _now_ns(self) -> int:
        return self._cycle * self._period_ns if self._timebase == "cycles" else time.monotonic_ns()

    def _send(self, frames: list[Frame]) -> None:
        try:
            self._send_frames(frames)
        except (can.CanError, OSError) as exc:
            raise DriveLinkLostError(f"drive node {self.node_id}: cannot send on "
                                     f"{self.bus.channel_info}: {one_line(exc)}") from None
        if self._pump is not None:
            self._pump()

    def _dispatch(self, frame: Frame, late: bool = False) -> None:
        can_id, data = frame
        n = self.node_id
        if can_id == self._tpdo1 or can_id == self._tpdo2:
            if len(data) < 6:
                self.stats.malformed_frames += 1
            elif late or not self._awaiting:
                self.stats.late_frames += 1
            elif can_id == self._tpdo1:
                self._rx_statusword, self._rx_position = struct.unpack_from("<Hi", data)
                self._got |= 1
            else:
                self._rx_velocity, self._rx_torque = struct.unpack_from("<ih", data)
                self._got |= 2
        elif can_id == 0x580 + n:
            self._sdo_inbox.append(data)
        elif can_id == 0x80 + n:
            self._on_emcy(data)
        elif can_id == 0x700 + n and len(data) >= 1:
            self._drive_heartbeat_ns = self._now_ns()
            if data[0] == 0x00 and self._enabled:
                self._rebooted = True
                self._event("drive.bootup", f"drive node {n} sent a boot-up message: it "
                            "restarted", level="error")

    def _take_waiting(self) -> None:
        """The frames already here for the cycle still awaited (without waiting for more)."""
        recv = self._recv_frame
        try:
            while self._got != 3 and (frame := recv(0)) is not None:
                self._dispatch(frame)
        except (can.CanError, OSError) as exc:
            raise DriveLinkLostError(f"drive node {self.node_id}: cannot read "
                                     f"{self.bus.channel_info}: {one_line(exc)}") from None
        self._awaiting = False

    def _drain(self) -> None:
        """Frames already waiting (late TPDOs, EMCY, heartbeats) before a new SYNC."""
        recv = self._recv_frame
        try:
            while (frame := recv(0)) is not None:
                self._dispatch(frame, late=True)
        except (can.CanError, OSError) as exc:
            raise DriveLinkLostError(f"drive node {self.node_id}: cannot read "
                                     f"{self.bus.channel_info}: {one_line(exc)}") from None

    def _on_emcy(self, data: bytes) -> None:
        if len(data) < 3:
            self.stats.malformed_frames += 1
            return
        code, register = struct.unpack_from("<HB", data)
        extra = data[3:8].hex()
        self.stats.emcy += 1
        name = EMCY_NAMES.get(code, "device specific")
        if code:
            self.last_emcy_code = code
        self._event("drive.emcy",
                    f"drive node {self.node_id} EMCY 0x{code:04X} ({name}), error register "
                    f"0x{register:02X}" + (f", data {extra}" if extra.strip("0") else ""),
                    level="info" if code == 0 else "error", code=code, register=register,
                    data_hex=extra)

    # ---------------------------------------------------------------------------- SDO
    def _sdo(self, request: bytes, what: str, segment: bool = False,
             timeout_s: float | None = None) -> bytes:
        timeout_s = self.config.sdo_timeout_s if timeout_s is None else timeout_s
        self._sdo_inbox.clear()
        self._send([(0x600 + self.node_id, request)])
        deadline = time.monotonic() + timeout_s
        while True:
            while self._sdo_inbox:
                response = self._sdo_inbox.pop(0)
                if len(response) != 8:
                    continue
                scs = response[0] & 0xE0
                if segment or response[1:4] == request[1:4]:
                    if scs == 0x80:
                        code = int.from_bytes(response[4:8], "little")
                        raise SdoAbortError(f"drive node {self.node_id} refused SDO {what}: "
                                            f"{SdoAbortedError(code)}", code)
                    return response
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DriveLinkLostError(
                    f"drive node {self.node_id} did not answer SDO {what} within "
                    f"{timeout_s:g} s on {self.bus.channel_info}")
            try:
                frame = self._recv_frame(min(remaining, 0.05))
            except (can.CanError, OSError) as exc:
                raise DriveLinkLostError(f"drive node {self.node_id}: cannot read "
                                         f"{self.bus.channel_info}: {one_line(exc)}") from None
            if frame is not None:
                self._dispatch(frame, late=True)

    def sdo_read(self, index: int, subindex: int = 0, timeout_s: float | None = None) -> bytes:
        """Upload one object (expedited or segmented); returns its raw bytes."""
        what = f"read 0x{index:04X}:{subindex:02X}"
        head = struct.pack("<BHB", 0x40, index, subindex)
        response = self._sdo(head + b"\0\0\0\0", what, timeout_s=timeout_s)
        command = response[0]
        if command & 0xE0 != 0x40:
            raise DriveError(f"drive node {self.node_id}: bad SDO response to {what}")
        if command & 0x02:  # expedited
            size = 4 - ((command >> 2) & 0x3) if command & 0x01 else 4
            return response[4:4 + size]
        data, toggle = bytearray(), 0
        while True:
            segment = self._sdo(bytes([0x60 | toggle]) + bytes(7), what, segment=True)
            if segment[0] & 0xE0 != 0x00 or segment[0] & 0x10 != toggle:
                raise DriveError(f"drive node {self.node_id}: bad SDO segment for {what}")
            data += segment[1:8 - ((segment[0] >> 1) & 0x7)]
            if segment[0] & 0x01:
                return bytes(data)
            toggle ^= 0x10

    def sdo_read_int(self, index: int, subindex: int = 0, fmt: str = "<I",
                     timeout_s: float | None = None) -> int:
        raw = self.sdo_read(index, subindex, timeout_s)
        size = struct.calcsize(fmt)
        if len(raw) < size:
            raise DriveError(f"drive node {self.node_id}: 0x{index:04X}:{subindex:02X} has "
                             f"{len(raw)} bytes, expected {size}")
        return struct.unpack_from(fmt, raw)[0]

    def sdo_write(self, index: int, subindex: int, value: int, fmt: str = "<I") -> None:
        """Expedited download of one value packed with ``fmt`` (1 to 4 bytes)."""
        data = struct.pack(fmt, value)
        command = 0x23 | ((4 - len(data)) << 2)
        request = struct.pack("<BHB", command, index, subindex) + data.ljust(4, b"\0")
        self._sdo(request, f"write 0x{index:04X}:{subindex:02X} = {value}")

    def nmt(self, command: int) -> None:
        self._send([(0x000, bytes([command, self.node_id]))])

    # ----------------------------------------------------------------- configuration
    def _bus_budget(self) -> BusBudget:
        c = self.config
        heartbeats = [p / 1000 for p in (c.heartbeat_period_ms, c.drive_heartbeat_ms) if p]
        frames = cia402_cyclic_frames(c.cycle_period_s, rpdo_bytes=self._rpdo1_map.size_bytes,
                                      tpdo_bytes=[pdo.size_bytes for pdo in TPDOS],
                                      heartbeat_periods_s=heartbeats)
        return cycle_budget(c.bitrate, c.cycle_period_s, frames)

    def _map_pdo(self, pdo: PdoMap) -> None:
        comm, mapping, cob_id = pdo.comm, pdo.mapping, pdo.cob_id(self.node_id)
        entries = pdo.mapping_values()
        self.sdo_write(comm, 1, cob_id | PDO_NOT_VALID)
        self.sdo_write(mapping, 0, 0, "<B")
        for sub, entry in enumerate(entries, start=1):
            self.sdo_write(mapping, sub, entry)
        self.sdo_write(mapping, 0, len(entries), "<B")
        self.sdo_write(comm, 2, 1, "<B")  # transmission type 1: every SYNC
        self.sdo_write(comm, 1, cob_id)

    def _disable_pdo(self, comm: int) -> None:
        """Invalidate a PDO we do not use; a drive without it is fine."""
        try:
            cob = self.sdo_read_int(comm, 1)
            if not cob & PDO_NOT_VALID:
                self.sdo_write(comm, 1, cob | PDO_NOT_VALID)
        except SdoAbortError as exc:
            if exc.code not in (0x0602_0000, 0x0609_0011):
                raise

    def configure(self) -> None:
        """Write the run's settings by SDO: mode, PDO map, cycle period, heartbeats, limits.
        The drive is in SWITCH ON DISABLED (after :meth:`open`)."""
        c, n = self.config, self.node_id
        device_type = self.sdo_read_int(0x1000, 0)
        if device_type & 0xFFFF != 402:
            raise DriveError(f"node {n} is not a CiA 402 drive (device type 0x{device_type:08X})")
        supported = self.sdo_read_int(0x6502, 0)
        if not supported & SUPPORTED_MODE_BITS[self.mode]:
            raise DriveError(f"drive node {n} does not support mode {c.mode.upper()} "
                             f"({self.mode}): 0x6502 = 0x{supported:08X}")
        self.nmt(NMT_PRE_OPERATIONAL)
        for comm in (0x1401, 0x1402, 0x1403, 0x1802, 0x1803):
            self._disable_pdo(comm)
        for pdo in (self._rpdo1_map, *TPDOS):
            self._map_pdo(pdo)
        self.sdo_write(0x1006, 0, round(c.cycle_period_s * 1e6))
        self.sdo_write(0x1017, 0, c.drive_heartbeat_ms, "<H")
        consumer = (c.heartbeat_id << 16) | c.heartbeat_timeout_ms if c.heartbeat_period_ms else 0
        self.sdo_write(0x1016, 1, consumer)
        self.sdo_write(0x6060, 0, self.mode, "<b")
        shown = self.sdo_read_int(0x6061, 0, "<b")
        if shown != self.mode:
            raise DriveStateError(f"drive node {n} shows mode {shown} after 0x6060 = {self.mode}")
        self.rated_current_ma = float(self.sdo_read_int(0x6075, 0))
        increments = self.sdo_read_int(0x608F, 1)
        revolutions = self.sdo_read_int(0x608F, 2)
        if not increments or revolutions != 1:
            raise DriveError(f"drive node {n}: encoder resolution 0x608F = {increments} "
                             f"increments / {revolutions} revolutions is not supported")
        self.increments_per_rev = increments
        max_torque = math.ceil(c.current_limit_ma * 1000.0 / self.rated_current_ma)
        if max_torque > 0xFFFF:
            raise ConfigError(f"current_limit_mA {c.current_limit_ma} is beyond what 0x6072 can "
                              f"hold with a rated current of {self.rated_current_ma} mA")
        self.sdo_write(0x6072, 0, max_torque, "<H")
        self.sdo_write(0x605A, 0, c.quick_stop_option, "<h")
        if self.mode == CSP:
            self.sdo_write(0x607A, 0, self.sdo_read_int(0x6064, 0, "<i"), "<i")
        else:
            self.sdo_write(0x6071, 0, 0, "<h")
        self._event("drive.configured",
                    f"drive node {n}: {c.mode.upper()} at {c.cycle_period_s * 1e6:g} us, "
                    f"limit {c.current_limit_ma:g} mA, {increments} increments/rev",
                    mode=c.mode, period_us=c.cycle_period_s * 1e6, rated_current_mA=
                    self.rated_current_ma, increments_per_rev=increments,
                    bus_budget=self.budget.summary())
        for warning in self.budget.warnings:
            self._event("drive.bus_budget", warning, level="warning")
        if c.heartbeat_period_ms and c.heartbeat_period_ms >= c.heartbeat_timeout_ms:
            self._event("drive.heartbeat_config",
                        f"master heartbeat every {c.heartbeat_period_ms} ms but the drive gives "
                        f"up after {c.heartbeat_timeout_ms} ms: it will fault", level="warning")

    def _statusword(self) -> int:
        return self.sdo_read_int(STATUSWORD, 0, "<H")

    def _reach(self) -> int:
        """The statusword by SDO; a node in NMT STOPPED (no SDO) is sent to PRE-OPERATIONAL.

        NMT is not sent first on purpose: a drive left enabled in OPERATIONAL may take leaving
        OPERATIONAL as a communication fault."""
        try:
            return self.sdo_read_int(STATUSWORD, 0, "<H", min(0.2, self.config.sdo_timeout_s))
        except DriveLinkLostError:
            self.nmt(NMT_PRE_OPERATIONAL)
        return self._statusword()

    def _let_time_pass(self) -> None:
        """While waiting for the drive: sleep, or in lockstep send a SYNC (the plant's clock)."""
        if self._pump is None:
            time.sleep(0.002)
            return
        self._send([self._sync])
        self._cycle += 1

    def _wait_state(self, wanted: str, why: str) -> int:
        deadline = time.monotonic() + self.config.state_timeout_s
        while True:
            statusword = self._statusword()
            if state_of(statusword) == wanted:
                return statusword
            if time.monotonic() > deadline:
                raise DriveStateError(
                    f"drive node {self.node_id} stuck in {state_of(statusword)} (statusword "
                    f"0x{statusword:04X}) waiting for {wanted} ({why}) after "
                    f"{self.config.state_timeout_s:g} s")
            self._let_time_pass()

    def open(self) -> None:
        """Reach the drive by SDO and leave it in SWITCH ON DISABLED (voltage disabled).

        A drive found in FAULT is left alone (DriveFaultError): clearing a fault is an explicit
        decision, :meth:`reset_fault`."""
        if self._closed:
            raise DriveError("the drive master is closed")
        self._latched, self._enabled, self._rebooted = None, False, False
        state = state_of(self._reach())
        if state in (FAULT, FAULT_REACTION_ACTIVE):
            code = self.sdo_read_int(0x603F, 0, "<H")
            name = EMCY_NAMES.get(code, "device specific")
            raise DriveFaultError(f"drive node {self.node_id} is in {state} (error code "
                                  f"0x{code:04X}, {name}): call reset_fault()", code)
        if state not in (SWITCH_ON_DISABLED, NOT_READY_TO_SWITCH_ON):
            self.sdo_write(CONTROLWORD, 0, CW_DISABLE_VOLTAGE, "<H")  # left enabled by someone
        self._wait_state(SWITCH_ON_DISABLED, "disable voltage")

    def enable(self) -> None:
        """NMT start, then the controlwords to OPERATION ENABLED; ``feedback`` is then the
        drive's, read by SDO. After :meth:`open` and :meth:`configure`."""
        self._enable()

    def _enable(self) -> Feedback:
        n = self.node_id
        self.nmt(NMT_START)
        for controlword, wanted in ENABLE_STEPS:
            self.sdo_write(CONTROLWORD, 0, controlword, "<H")
            self._wait_state(wanted, f"controlword 0x{controlword:04X}")
        self._enabled = True
        self.watchdog.success()
        self._next_heartbeat_ns = None
        self._drive_heartbeat_ns = self._now_ns()  # the heartbeat is watched from here on
        feedback = self.feedback = self._feedback_by_sdo()
        position = feedback.position_deg
        self._event("drive.enabled", f"drive node {n} OPERATION ENABLED at {position:.4f} deg",
                    position_deg=position)
        return feedback

    def start(self) -> Feedback:
        """:meth:`open`, :meth:`configure`, :meth:`enable`; return the drive's feedback."""
        self.open()
        self.configure()
        return self._enable()

    def _feedback_by_sdo(self) -> Feedback:
        self._rx_statusword = self._statusword()
        self._rx_position = self.sdo_read_int(0x6064, 0, "<i")
        self._rx_velocity = self.sdo_read_int(0x606C, 0, "<i")
        self._rx_torque = self.sdo_read_int(0x6077, 0, "<h")
        return self._make_feedback(fresh=True, rtt_us=0.0)

    def reset_fault(self) -> Feedback:
        """Explicit recovery: reconnect if the link was lost, clear a drive FAULT (rising edge
        of controlword bit 7), then :meth:`start` again."""
        if self._closed:
            raise DriveError("the drive master is closed")
        if isinstance(self._latched, DriveLinkLostError) and self._bus_factory is not None:
            with contextlib.suppress(Exception):  # the old connection is gone anyway
                self.bus.shutdown()
            self._use_bus(self._bus_factory())
        self._latched = None
        self._rebooted = False
        self._drain()
        state = state_of(self._reach())
        if state == FAULT_REACTION_ACTIVE:
            self._wait_state(FAULT, "fault reaction")
            state = FAULT
        if state == FAULT:
            self.sdo_write(CONTROLWORD, 0, CW_DISABLE_VOLTAGE, "<H")
            self.sdo_write(CONTROLWORD, 0, CW_FAULT_RESET, "<H")
            self._wait_state(SWITCH_ON_DISABLED, "fault reset")
            self.sdo_write(CONTROLWORD, 0, CW_DISABLE_VOLTAGE, "<H")
            self._event("drive.fault_reset", f"drive node {self.node_id}: fault reset")
        return self.start()

    # -------------------------------------------------------------------- cyclic path
    def _check_latched(self) -> None:
        if self._latched is not None:
            error = copy.copy(self._latched)  # same type and data, a note on the message
            error.args = (f"{self._latched} (latched: call reset_fault())",)
            raise error
        if not self._enabled:
            raise DriveStateError(f"drive node {self.node_id} is not enabled: call start()")

    def _send_cycle(self, controlword: int, target: int) -> None:
        try:
            if self._awaiting:  # the last cycle's answer was never asked for: what came is its
                self._take_waiting()
            if self._got != 3:  # the last pair is missing: what comes of it now is late
                self._drain()
        except DriveLinkLostError as exc:
            self._lose_link(one_line(exc))
        rpdo = (self._rpdo1, self._rpdo_layout.pack(controlword, target))
        now = self._now_ns()
        frames = [rpdo, self._sync]
        period_ms = self.config.heartbeat_period_ms
        if period_ms and (self._next_heartbeat_ns is None or now >= self._next_heartbeat_ns):
            frames.append(self._heartbeat)
            self._next_heartbeat_ns = now + period_ms * 1_000_000
        self._got = 0
        self._awaiting = True
        self._sent_ns = time.perf_counter_ns()
        try:
            self._send(frames)
        except DriveLinkLostError as exc:
            self._awaiting = False
            self._lose_link(one_line(exc))
        self._cycle += 1

    def _receive(self) -> Feedback:
        if not self._awaiting:  # nothing sent since the last read: the same feedback again
            if self.feedback is None:
                raise DriveStateError("no feedback yet: call start()")
            return self.feedback
        # measured from the SYNC, as drive.toml documents it: in the split form the TPDOs have
        # travelled while the loop slept, and a late pair costs the tick only what is left
        deadline_ns = self._sent_ns + self._rx_timeout_ns
        recv = self._recv_frame
        clock = time.perf_counter_ns
        # a wait of a cycle or so is spent polling: a thread blocked in select() is woken up
        # 50 us to several hundred us after the frame arrives (more on a virtual machine)
        poll = self._rx_timeout_ns <= POLL_WAIT_MAX_NS
        try:
            while self._got != 3:
                remaining = (deadline_ns - clock()) / 1e9
                frame = recv(0.0 if poll else max(0.0, remaining))
                if frame is not None:
                    self._dispatch(frame)
                elif remaining <= 0:
                    break
        except (can.CanError, OSError) as exc:
            self._awaiting = False
            self._lose_link(f"cannot read {self.bus.channel_info}: {one_line(exc)}")
        self._awaiting = False
        stats = self.stats
        stats.cycles += 1
        if self._rebooted:
            self._lose_link("the drive restarted (boot-up message)")
        silent_ns = self._now_ns() - self._drive_heartbeat_ns
        if self.config.drive_heartbeat_ms and silent_ns > self._heartbeat_timeout_ns:
            self._lose_link(f"no heartbeat for {silent_ns / 1e6:.0f} ms (it beats every "
                            f"{self.config.drive_heartbeat_ms} ms)")
        if self._got == 3:
            stats.fresh += 1
            self.watchdog.success()
            rtt_us = (time.perf_counter_ns() - self._sent_ns) / 1e3
            self.feedback = self._make_feedback(fresh=True, rtt_us=rtt_us)
        else:
            stats.stale += 1
            lost = self.watchdog.failure()
            stats.longest_stale_run = self.watchdog.longest_run
            previous = self.feedback
            if previous is None:
                self.feedback = self._make_feedback(fresh=False, rtt_us=0.0)
            else:
                self.feedback = Feedback(
                    previous.position_deg, previous.velocity_deg_s, previous.current_ma,
                    previous.statusword, previous.position_increments, self._cycle,
                    self._now_ns(), False, 0.0, self._command_ma)
            if lost:
                self._lose_link(f"no TPDO for {self.watchdog.run} cycles")
        return self.feedback

    def _make_feedback(self, fresh: bool, rtt_us: float) -> Feedback:
        raw, increments = self._rx_position, self.increments_per_rev
        if self._last_raw is not None:
            step = raw - self._last_raw
            if step > increments // 2:
                self._turns -= 1
            elif step < -(increments // 2):
                self._turns += 1
        self._last_raw = raw
        scale = 360.0 / increments
        return Feedback(
            position_deg=(self._turns * increments + raw) * scale,
            velocity_deg_s=self._rx_velocity * scale,
            current_ma=self._rx_torque * self.rated_current_ma / 1000.0,
            statusword=self._rx_statusword,
            position_increments=raw,
            cycle=self._cycle,
            t_ns=self._now_ns(),
            fresh=fresh,
            rtt_us=rtt_us,
            command_ma=self._command_ma,
        )

    def _check_operation(self, feedback: Feedback) -> Feedback:
        state = feedback.state
        if state == OPERATION_ENABLED or not feedback.fresh:
            return feedback
        n = self.node_id
        if state in (FAULT, FAULT_REACTION_ACTIVE):
            code = self.last_emcy_code
            error: DriveError = DriveFaultError(
                f"drive node {n} reports {state} (statusword 0x{feedback.statusword:04X}, last "
                f"EMCY 0x{code:04X} {EMCY_NAMES.get(code, 'device specific')})", code)
            self._event("drive.fault", str(error), level="error", code=code)
            self._enabled = False
        else:
            error = DriveStateError(f"drive node {n} left OPERATION ENABLED: now {state} "
                                    f"(statusword 0x{feedback.statusword:04X})")
            self._event("drive.state", str(error), level="error", state=state)
            self.safe_state()
        self._latched = error
        raise error

    def _lose_link(self, reason: str) -> None:
        error = DriveLinkLostError(f"drive node {self.node_id} link lost: {reason}")
        self._latched = error
        self._event("drive.link_lost", str(error), level="error", cycle=self._cycle)
        if self._enabled:  # best effort, without waiting: quick stop, then disable voltage
            self._enabled = False
            for controlword in (CW_QUICK_STOP, CW_DISABLE_VOLTAGE):
                try:
                    self._send([(self._rpdo1, self._rpdo_layout.pack(controlword, 0)),
                                self._sync])
                except DriveError:
                    break
        raise error

    def _torque_units(self, current_ma: float) -> int:
        if not math.isfinite(current_ma):
            raise DriveError(f"drive node {self.node_id}: refusing a non-finite current "
                             f"command ({current_ma!r})")
        limit = self.config.current_limit_ma
        clamped = min(max(current_ma, -limit), limit)
        if clamped != current_ma:
            self.stats.clamped_commands += 1
        self._command_ma = clamped
        return round(clamped * 1000.0 / self.rated_current_ma)

    def send_command(self, current_ma: float) -> None:
        """CST: send the current command (clamped to the limit) and a SYNC."""
        self._check_latched()
        if self.mode != CST:
            raise DriveStateError("send_command() needs mode 'cst'; use send_position()")
        self._send_cycle(CW_ENABLE_OPERATION, self._torque_units(current_ma))

    def send_position(self, target_deg: float) -> None:
        """CSP: send the position target (multi-turn degrees) and a SYNC.

        On the wire the target is modulo one turn, like the position: the drive goes the short
        way round, so consecutive targets must differ by less than half a turn."""
        self._check_latched()
        if self.mode != CSP:
            raise DriveStateError("send_position() needs mode 'csp'; use send_command()")
        if not math.isfinite(target_deg):
            raise DriveError(f"drive node {self.node_id}: refusing a non-finite position target")
        increments = round(target_deg / 360.0 * self.increments_per_rev) % self.increments_per_rev
        self._command_ma = 0.0
        self._send_cycle(CW_ENABLE_OPERATION, increments)

    def receive_feedback(self) -> Feedback:
        """The TPDOs of the last SYNC (waits until ``rx_timeout`` after that SYNC); raises on
        fault or loss.

        Without a cycle sent since the last call it returns the last feedback again (the one
        of :meth:`start` before the first cycle)."""
        self._check_latched()
        return self._check_operation(self._receive())

    def exchange(self, current_ma: float) -> Feedback:
        """One CST cycle: command, SYNC, feedback."""
        self.send_command(current_ma)
        return self.receive_feedback()

    def exchange_position(self, target_deg: float) -> Feedback:
        """One CSP cycle: position target, SYNC, feedback."""
        self.send_position(target_deg)
        return self.receive_feedback()

    def cycle(self, controlword: int, target: int = 0) -> Feedback:
        """One raw cycle with any controlword and raw target (for commissioning and tests).

        No state check; the TPDO watchdog still applies."""
        if self._latched is not None:
            self._check_latched()
        self._command_ma = 0.0
        self._send_cycle(controlword, target)
        return self._receive()

    # ------------------------------------------------------------------------- stops
    def safe_state(self) -> None:
        """Quick stop (cyclic, until standstill or the time-out), then disable voltage.

        Idempotent and silent: failures become a ``drive.safe_stop_failed`` event."""
        if self._closed or not self._enabled:
            return
        self._enabled = False
        c = self.config
        try:
            cycles = max(1, math.ceil(c.quick_stop_timeout_s / c.cycle_period_s))
            pace = self._timebase == "monotonic" and self._pump is None
            next_tick = time.monotonic()
            state = "UNKNOWN"
            for _ in range(cycles):
                feedback = self.cycle(CW_QUICK_STOP, self._hold_target())
                state = feedback.state
                if feedback.fresh and (state in (SWITCH_ON_DISABLED, FAULT) or (
                        state == QUICK_STOP_ACTIVE
                        and abs(feedback.velocity_deg_s) < c.standstill_deg_s)):
                    break
                if pace:
                    next_tick += c.cycle_period_s
                    time.sleep(max(0.0, next_tick - time.monotonic()))
            state = self.cycle(CW_DISABLE_VOLTAGE, self._hold_target()).state
            if state == OPERATION_ENABLED:  # it ignored both: only its SYNC watchdog is left
                self._event("drive.safe_stop_failed", f"drive node {self.node_id} ignored quick "
                            "stop and disable voltage: still OPERATION ENABLED; no more SYNC, "
                            "so its SYNC watchdog must fault it", level="error", state=state)
                return
            self._event("drive.safe_stop", f"drive node {self.node_id} stopped: {state}",
                        state=state)
        except DriveError as exc:
            self._event("drive.safe_stop_failed", f"drive node {self.node_id}: safe stop "
                        f"incomplete: {one_line(exc)}", level="error")

    def _hold_target(self) -> int:
        if self.mode == CSP and self.feedback is not None:
            return self.feedback.position_increments
        return 0

    def disconnect(self) -> None:
        """Release the bus and anything the master was built with (the emulator); idempotent.
        :meth:`close` (safe stop, then this) is the usual way out."""
        if self._closed:
            return
        self._closed = True
        self._enabled = False
        self.bus.shutdown()
        for closer in self._closers:
            closer()


def one_line(exc: BaseException) -> str:
    """An exception's message on one line: python-can's socketcand interface appends
    ``traceback.format_exc()`` to its errors, which is cut off here."""
    text = str(exc).split("Traceback (most recent call last)")[0].strip()
    return " ".join(text.splitlines()[0].split()) if text else type(exc).__name__


# ---------------------------------------------------------------------------- factories
def open_socketcand(url: str, config: DriveMasterConfig | None = None, *,
                    on_event: EventSink = no_event,
                    closers: tuple[Callable[[], None], ...] = ()) -> CanDriveMaster:
    """A master (not started) reaching the drive through a socketcand gateway,
    ``socketcand://HOST:PORT[/CHANNEL]`` (channel: ``config.channel`` if none); ``closers``
    run when the master disconnects."""
    config = config or DriveMasterConfig()
    parts = urlsplit(url)
    try:
        host, port = parts.hostname, parts.port
    except ValueError:
        host, port = None, None
    if parts.scheme != "socketcand" or not host or port is None:
        raise ConfigError(f"drive '{url}': expected socketcand://HOST:PORT[/CHANNEL]")
    channel = parts.path.strip("/") or config.channel

    def connect() -> can.BusABC:
        try:
            return SocketcandBus(channel, host, port)
        except can.CanError as exc:  # its message names the gateway and the bus
            raise DriveLinkLostError(one_line(exc)) from None

    return CanDriveMaster(connect(), config, on_event=on_event, bus_factory=connect, url=url,
                          closers=closers)


def open_interface(url: str, config: DriveMasterConfig | None = None, *,
                   on_event: EventSink = no_event) -> CanDriveMaster:
    """A master (not started) on a python-can interface, ``INTERFACE://CHANNEL``
    (``socketcan://can0``, ``pcan://PCAN_USBBUS1``, ``virtual://name``...)."""
    config = config or DriveMasterConfig()
    parts = urlsplit(url)
    interface, channel = parts.scheme, (parts.netloc + parts.path).strip("/")
    if not interface or not channel:
        raise ConfigError(f"drive '{url}': expected INTERFACE://CHANNEL")
    bitrate = config.bitrate

    def open_bus() -> can.BusABC:
        try:
            return can.Bus(interface=interface, channel=channel, bitrate=bitrate)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise DriveLinkLostError(f"cannot open CAN interface {interface!r} channel "
                                     f"{channel!r}: {one_line(exc)}") from None

    return CanDriveMaster(open_bus(), config, on_event=on_event, bus_factory=open_bus, url=url)
