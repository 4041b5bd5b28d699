"""The CiA 402 master: one drive on one bus, composed of the CiA 301 services.

Everything happens in the caller's thread (no ``Notifier``, whose thread dies silently when a
listener raises). Use from a loop task split over two phases, which lets the TPDOs travel
while the loop sleeps::

    feedback = master.receive_feedback()            # read: the previous SYNC's TPDOs
    master.send_set_point(value)                    # write: RPDO + SYNC

or in one call (``exchange``) for commissioning and tests. Either way ``feedback`` reflects
the command of the previous cycle applied for one period (``x(k+1) = A x(k) + B u(k)``).
The set point is the mode's (a current, a position or a velocity: :mod:`.setpoint`), the
profile moves' and the homing's cycles :mod:`.motion`'s; an object the drive lacks is neither
read nor written (:mod:`.objects`). Safety lives here: currents are clamped to
``current_limit_mA``; no TPDO for ``stale_cycles`` cycles, a send error, a silent heartbeat or
a drive reboot -> link lost; a FAULT or any state other than OPERATION ENABLED -> error. Each
of these puts the drive into its safe state (quick stop, then disable voltage), emits an event
and latches: every later cyclic call raises until :meth:`CanDriveMaster.recover` recovers
explicitly. EMCY frames become ``drive.emcy`` events through ``on_event``.

The master is a :class:`hil.contracts.Device`: :meth:`~CanDriveMaster.open` (SDO, voltage
disabled), :meth:`~CanDriveMaster.configure` (the drive's description and scaling, mode, PDO
map, heartbeats, limits), :meth:`~CanDriveMaster.enable` (OPERATION ENABLED),
:meth:`~CanDriveMaster.safe_state`, :meth:`~CanDriveMaster.close`. Its time is a
:class:`~hil.drivers.canopen.state.MasterClock` (the monotonic clock unless a rig gives another).
"""

from __future__ import annotations

import contextlib
import copy
import math
import struct
from collections.abc import Callable, Iterator
from dataclasses import replace
from functools import partial
from typing import Any, NoReturn

from hil.contracts import Device, EventSink, LinkWatchdog, no_event
from hil.drivers.can_bus_time import BusBudget
from hil.drivers.canopen.bus_plan import plan_axes
from hil.drivers.canopen.clocks import ClockSwitch, MonotonicClock
from hil.drivers.canopen.config import DriveMasterConfig
from hil.drivers.canopen.current_limit import (
    CurrentLimit,
    max_torque_units,
    read_current_limit,
    unenforced_text,
)
from hil.drivers.canopen.cyclic import CyclicExchange, Feedback, LinkStats
from hil.drivers.canopen.eds import DriveDescription, modes_problem
from hil.drivers.canopen.errors import (
    BusSharedError,
    DriveError,
    DriveFaultError,
    DriveLinkLostError,
    DriveStateError,
)
from hil.drivers.canopen.link import Link
from hil.drivers.canopen.nmt import HeartbeatProducer, HeartbeatWatch, Nmt
from hil.drivers.canopen.objects import DriveObjects, Notices, without_text
from hil.drivers.canopen.pdo import PdoConfigurator, tpdo_maps, unused_pdos, without_object
from hil.drivers.canopen.profile import profile_writes
from hil.drivers.canopen.run_settings import RunSettings
from hil.drivers.canopen.scaling import DriveScaling, read_scaling
from hil.drivers.canopen.scan import discover
from hil.drivers.canopen.sdo import SdoChannel, SdoClient
from hil.drivers.canopen.setpoint import holding_value, wire_format, wire_value
from hil.drivers.canopen.state import (
    MasterClock,
    NmtCommands,
    SdoWords,
    StateControl,
    StateWords,
)
from hil.drivers.canopen.stopping import (
    MAY_STILL_MOVE,
    confirm_stopped,
    last_report,
    stop_together,
)
from hil.protocols.can_frames import Frame
from hil.protocols.cia301 import (
    CONSUMER_HEARTBEAT,
    CYCLE_PERIOD,
    DEVICE_TYPE,
    EMCY_BASE,
    HEARTBEAT_BASE,
    NMT_COB_ID,
    NMT_ENTER_PRE_OPERATIONAL,
    NMT_START,
    PRODUCER_HEARTBEAT,
    SYNC_COB_ID,
    SYNC_COUNTER_OVERFLOW,
    SdoAbortError,
    emcy_text,
)
from hil.protocols.cia402 import (
    CW_DISABLE_VOLTAGE,
    CW_ENABLE_OPERATION,
    CW_QUICK_STOP,
    ERROR_CODE,
    FAULT,
    FAULT_REACTION_ACTIVE,
    MAX_TORQUE,
    MODES_DISPLAY,
    MODES_OF_OPERATION,
    NOT_READY_TO_SWITCH_ON,
    OPERATION_ENABLED,
    OPERATION_MODES,
    POSITION_ACTUAL,
    QUICK_STOP_ACTIVE,
    QUICK_STOP_OPTION,
    SUPPORTED_MODES,
    SWITCH_ON_DISABLED,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
    mode_switch_allowed,
    state_of,
)

CIA402_DEVICE_TYPE = 402
#: how long :meth:`CanDriveMaster.prime` waits for the first cycle's answer
PRIME_TIMEOUT_S = 0.1


class CanDriveMaster(Device):
    """CiA 402 master for one drive on a :class:`~hil.drivers.canopen.link.CanLink` (a
    :class:`~hil.contracts.Device`). :meth:`start` (:meth:`open`, :meth:`configure`,
    :meth:`enable`) comes first. ``url`` names the drive in events and errors."""

    def __init__(self, link: Link, config: DriveMasterConfig | None = None, *,
                 on_event: EventSink = no_event, clock: MasterClock | None = None,
                 closers: tuple[Callable[[], None], ...] = (), url: str | None = None) -> None:
        self.config = config = config or DriveMasterConfig()
        self.link = link
        # frames only a master sends: heard from anyone else, another master drives the bus
        link.watched_ids = watched = frozenset(
            (SYNC_COB_ID, NMT_COB_ID, HEARTBEAT_BASE + config.heartbeat_id))
        self._url = url if url is not None else link.name
        self.node_id = n = config.node_id
        self.operation = OPERATION_MODES[config.mode]  # the mode configure() sets
        self._clock = ClockSwitch(clock or MonotonicClock())
        self._on_event = on_event
        self._closers = closers
        self.watchdog = LinkWatchdog(config.stale_cycles, "cycles without a TPDO")
        self.heartbeat_watch = HeartbeatWatch(n, config.drive_heartbeat_ms, self._clock.time_ns)
        # the frames that are not the cyclic TPDOs, by COB-ID (the watched ids over any other)
        self._frame_handlers: dict[int, Callable[[Frame], None]] = {
            EMCY_BASE + n: lambda frame: self._on_emcy(frame[1]),
            self.heartbeat_watch.cob_id: self._on_heartbeat,
            **dict.fromkeys(watched, self._on_watched),
        }
        # the drive's SDO and NMT, for everyone (``master.sdo.read_int(...)``); a refusal of a
        # download queued for the cyclic exchange (``sdo.queue_write``) is raised by the next
        # receive_feedback()
        self.sdo: SdoChannel = self._new_sdo(link)
        self.objects = DriveObjects(self.sdo)  # which the drive has (its EDS's, at open())
        self.nmt: NmtCommands = self._new_nmt(link)
        self._tpdo_maps = tpdo_maps(config.sync_echo, config.tpdo_layout)
        self.cyclic = self._new_cyclic(link)
        self.states = StateControl(self._new_words(), self.nmt, self._clock,
                                   config.state_timeout_s, config.sdo_timeout_s, n)
        self.budget: BusBudget = plan_axes(config, ["axis"]).budget
        self.description: DriveDescription | None = None
        self._limit: CurrentLimit | None = None   # read at open()
        self._units_from: dict[str, str] = {}      # where each scaling value came from
        # what hil does without because the drive lacks an object (events, terminal lines)
        self.notices = Notices(self._event)
        # every setting this master writes, put back when it lets the drive go
        self.settings = RunSettings(self.sdo, n, self._event)
        self.last_emcy_code = 0
        self._enabled = False
        self._lost_driving = False  # the link was lost while the drive was enabled
        self._watch_from_next_cycle = False  # enabled: the heartbeat watched from the 1st SYNC
        self._latched: DriveError | SdoAbortError | None = None
        self._operating_word = -1  # the last statusword found OPERATION ENABLED
        self.foreign: str | None = None  # another master heard on the bus: the run stops
        # told each cycle of a safe stop (quick stop, disable voltage): what the drive reported
        self.on_stop_cycle: Callable[[Feedback], None] | None = None
        self._stop_target = 0  # what the stop cycles send as the target (begin_stop)
        self._closed = False

    # -- the transport's services (another transport's master builds its own) ---------------
    def _new_sdo(self, link: Link) -> SdoChannel:
        """The CAN SDO client to the drive; its answers among the frames the master reads."""
        c = self.config
        sdo = SdoClient(link, c.node_id, c.sdo_timeout_s, self._other_frame,
                        gone_after_s=c.lockstep_timeout_s if c.lockstep else None,
                        census=partial(discover, link))
        self._frame_handlers[sdo.response_id] = lambda frame: sdo.on_response(frame[1])
        self._queued_sdo_frames = sdo.next_frames
        return sdo

    def _new_nmt(self, link: Link) -> NmtCommands:
        return Nmt(link, self.config.node_id)

    def _new_words(self) -> StateWords:
        """The controlword and statusword by SDO (no RPDO goes out before the drive is
        enabled)."""
        return SdoWords(self.sdo, self._clock)

    def _new_cyclic(self, link: Link) -> CyclicExchange:
        """RPDO + SYNC out, TPDOs in (:class:`CyclicExchange`), a queued SDO download with
        them."""
        c = self.config
        cyclic = CyclicExchange(
            link, c.node_id, self.operation.rpdo1(), self._tpdo_maps,
            rx_timeout_s=c.rx_timeout_s, silence_is_gone=c.lockstep,
            period_s=c.cycle_period_s,
            watchdog=self.watchdog,
            heartbeat=HeartbeatProducer(c.heartbeat_id, c.heartbeat_period_ms,
                                        self._clock.time_ns),
            now_ns=self._clock.time_ns, other=self._other_frame)
        cyclic.extra_frames = self._queued_sdo_frames
        return cyclic

    # -- what the master knows -------------------------------------------------------------
    @property
    def url(self) -> str:
        return self._url

    @property
    def clock(self) -> MasterClock:
        """The time the master goes by (its watchdogs, heartbeats, state waits)."""
        return self._clock.clock

    @clock.setter
    def clock(self, clock: MasterClock) -> None:
        self._clock.clock = clock

    @property
    def link_up(self) -> bool:
        """False from a lost link (no TPDO, send error, reboot) until :meth:`recover`."""
        return not self.watchdog.lost and not isinstance(self._latched, DriveLinkLostError)

    @property
    def stats(self) -> LinkStats:
        return self.cyclic.stats

    @property
    def feedback(self) -> Feedback | None:
        return self.cyclic.feedback

    @property
    def scaling(self) -> DriveScaling:
        """The drive's units, as read at :meth:`configure`."""
        return self.cyclic.scaling

    @property
    def mode(self) -> int:
        """The 0x6060 code of the mode configure() sets."""
        return self.operation.code

    @property
    def increments_per_rev(self) -> int:
        return self.scaling.increments_per_rev

    @property
    def rated_current_ma(self) -> float:
        return self.scaling.rated_current_ma

    def describe(self) -> dict[str, Any]:
        """What the session records of the drive: node, mode, scaling, current limit,
        description."""
        return {"url": self.url, "node_id": self.node_id, "mode": self.operation.name,
                "scaling": self.scaling.describe(), "scaling_from": self._units_from,
                "current_limit": self.limit.describe(),
                "eds": self.description.describe() if self.description else None}

    def _event(self, kind: str, message: str, level: str = "info", **data: Any) -> None:
        self._on_event(kind, message, level=level, source=f"drive{self.node_id}", **data)

    # -- frames that are not the cyclic TPDOs ------------------------------------------------
    def _other_frame(self, frame: Frame) -> None:
        handler = self._frame_handlers.get(frame[0])
        if handler is not None:
            handler(frame)

    def _on_watched(self, frame: Frame) -> None:
        if not self.link.own_echo(frame):
            self._foreign_frame(frame[0])

    def _on_heartbeat(self, frame: Frame) -> None:
        if self.heartbeat_watch.on_frame(frame[1], watching=self._enabled):
            self._event("drive.bootup", f"drive node {self.node_id} sent a boot-up message: "
                        "it restarted", level="error")

    def _foreign_frame(self, can_id: int) -> None:
        """A SYNC, an NMT command or a heartbeat with this master's id that this master did
        not send: another master drives the bus (it would fight this one for the drive)."""
        if self.foreign is not None:
            return
        what = {SYNC_COB_ID: "a SYNC", NMT_COB_ID: "an NMT command"}.get(
            can_id, f"a heartbeat with this master's node id {self.config.heartbeat_id}")
        self.foreign = (f"another master on {self.url}: {what} (0x{can_id:03X}) this master "
                        "did not send; one master per bus")
        self._event("bus.foreign_master", self.foreign, level="error", cob_id=can_id)

    def _on_emcy(self, data: bytes) -> None:
        if len(data) < 3:
            self.stats.malformed_frames += 1
            return
        code, register = struct.unpack_from("<HB", data)
        extra = data[3:8].hex()
        if code:  # 0x0000 "error reset" reports the end of an error, not one
            self.last_emcy_code = code
            if self._enabled:  # one from before this master drove it is history, not a fault
                self.stats.emcy += 1  # of this run (it is still an event)
        self._event("drive.emcy",
                    f"drive node {self.node_id} EMCY {emcy_text(code)}, error register "
                    f"0x{register:02X}" + (f", data {extra}" if extra.strip("0") else ""),
                    level="info" if code == 0 or not self._enabled else "error", code=code,
                    register=register, data_hex=extra, while_driving=self._enabled)

    # -- configuration --------------------------------------------------------------------------
    def _check_mode(self) -> None:
        """The node is a CiA 402 drive that supports the mode (0x6502, where it has one)."""
        n = self.node_id
        device_type = self.sdo.read_int(DEVICE_TYPE, 0)
        if device_type & 0xFFFF != CIA402_DEVICE_TYPE:
            raise DriveError(f"node {n} is not a CiA 402 drive (device type 0x{device_type:08X})")
        supported = self.objects.read(SUPPORTED_MODES, 0)
        if supported is None:
            self.notices.tell("drive.object_missing", without_text(n, SUPPORTED_MODES, 0))
        elif (problem := modes_problem(supported, self.operation)) is not None:
            raise DriveError(f"drive node {n}: {problem}")

    def configure(self) -> None:
        """Check the drive (device type, modes), then write the run's settings by SDO: mode,
        PDO map, cycle period, heartbeats, limits, the mode's profile (configured values).
        An object the drive lacks is not written: hil does without it and says so
        (:attr:`notices`). The drive is in SWITCH ON DISABLED (after :meth:`open`)."""
        c, n, sdo, mode = self.config, self.node_id, self.sdo, self.operation
        self._check_mode()
        profile = profile_writes(self.objects, mode, c.profile, self.scaling)
        scaling, limit = self.scaling, self.limit
        self._configure_transport()
        self._write_setting(MODES_OF_OPERATION, 0, mode.code, "<b")
        self._confirm_mode()
        if limit.unenforced:
            self.notices.tell("drive.limit_unenforced", unenforced_text(n, mode, limit))
        else:
            self._write_setting(MAX_TORQUE, 0, max_torque_units(limit, scaling, n), "<H")
        self._write_where_present(QUICK_STOP_OPTION, 0, c.quick_stop_option, "<h")
        if mode.set_point is not None:
            index, subindex, _ = mode.set_point
            self._write_setting(index, subindex, holding_value(
                mode, lambda: sdo.read_int(POSITION_ACTUAL, 0, "<i")), wire_format(mode))
        for index, subindex, value, fmt in profile:
            self._write_setting(index, subindex, value, fmt)
        self._event("drive.configured",
                    f"drive node {n}: {mode.short} at {c.cycle_period_s * 1e6:g} us, "
                    f"limit {limit.applied_ma:g} mA, {scaling.increments_per_rev} "
                    f"increments/rev, rated {scaling.rated_current_ma:g} mA",
                    mode=mode.name, period_us=c.cycle_period_s * 1e6,
                    current_limit=limit.describe(),
                    rated_current_mA=scaling.rated_current_ma,
                    increments_per_rev=scaling.increments_per_rev,
                    scaling=scaling.describe(), bus_budget=self.budget.summary())
        for warning in self.budget.warnings:
            self._event("drive.bus_budget", warning, level="warning")
        if c.heartbeat_period_ms and c.heartbeat_period_ms >= c.heartbeat_timeout_ms:
            self._event("drive.heartbeat_config",
                        f"master heartbeat every {c.heartbeat_period_ms} ms but the drive gives "
                        f"up after {c.heartbeat_timeout_ms} ms: it will fault", level="warning")

    def _confirm_mode(self) -> None:
        """The drive shows the mode written (0x6061 after 0x6060), else a DriveStateError."""
        shown = self._mode_shown()
        if shown != self.operation.code:
            raise DriveStateError(f"drive node {self.node_id} shows mode {shown} after 0x6060 "
                                  f"= {self.operation.code}")

    def _mode_shown(self) -> int:
        """The mode the drive shows (0x6061)."""
        return self.sdo.read_int(MODES_DISPLAY, 0, "<b")

    def _configure_transport(self) -> None:
        """What :meth:`configure` writes for CAN: NMT pre-operational, the PDO maps (and the
        SYNC counter for ``sync_echo``), the cycle period, the heartbeats. Another transport's
        master writes its own here."""
        c, n, sdo = self.config, self.node_id, self.sdo
        self.nmt.command(NMT_ENTER_PRE_OPERATIONAL)
        if not self.objects.has(TORQUE_ACTUAL):  # its TPDOs carry what it has
            self.notices.tell("drive.object_missing", without_text(n, TORQUE_ACTUAL, 0))
            self._tpdo_maps = without_object(self._tpdo_maps, TORQUE_ACTUAL)
            self.cyclic.use_tpdos(self._tpdo_maps)
        pdos = PdoConfigurator(sdo, n, self._write_setting)
        if c.sync_echo is not None:
            pdos.start_sync_counter(self.objects.has(CYCLE_PERIOD),
                                    self.objects.has(SYNC_COUNTER_OVERFLOW))
        for comm in unused_pdos(self._tpdo_maps):
            pdos.disable(comm)
        for pdo in (self.operation.rpdo1(), *self._tpdo_maps):
            pdos.map(pdo)
        self.cyclic.echo = c.sync_echo is not None
        self._write_where_present(CYCLE_PERIOD, 0, round(c.cycle_period_s * 1e6))
        if not self._write_where_present(PRODUCER_HEARTBEAT, 0, c.drive_heartbeat_ms, "<H"):
            self.heartbeat_watch.period_ms = 0  # no heartbeat to watch
        consumer = (c.heartbeat_id << 16) | c.heartbeat_timeout_ms if c.heartbeat_period_ms else 0
        self._write_where_present(CONSUMER_HEARTBEAT, 1, consumer)

    def _write_where_present(self, index: int, subindex: int, value: int,
                             fmt: str = "<I") -> bool:
        """:meth:`_write_setting` where the drive has the object (else what hil does without
        it is told); whether it was written."""
        if self.objects.has(index, subindex):
            self._write_setting(index, subindex, value, fmt)
            return True
        self.notices.tell("drive.object_missing", without_text(self.node_id, index, subindex))
        return False

    def use_mode(self, name: str) -> None:
        """Drive in mode ``name`` (of :data:`~hil.protocols.cia402.OPERATION_MODES`) from the
        next :meth:`configure` on, which maps its RPDO, writes 0x6060 and waits for 0x6061 to
        show it. Only while the drive is not enabled: where CiA 402 lets any mode follow any
        other (:func:`~hil.protocols.cia402.mode_switch_allowed`)."""
        target = OPERATION_MODES[name]
        if self.enabled and not mode_switch_allowed(OPERATION_ENABLED, self.operation, target,
                                                    standing=False):
            raise DriveStateError(f"drive node {self.node_id} is enabled in "
                                  f"{self.operation.short}: it switches to {target.short} "
                                  "once stopped (the master maps its RPDO anew)")
        self.operation = target
        self.cyclic.use_rpdo(target.rpdo1())

    def _write_setting(self, index: int, subindex: int, value: int, fmt: str = "<I") -> None:
        """Write one setting of this run to the drive (SDO): every object :meth:`configure`
        sets goes through here, kept to be put back (:attr:`settings`)."""
        self.settings.write(index, subindex, value, fmt)

    # -- life cycle -----------------------------------------------------------------------------
    def open(self) -> None:
        """Check the drive's EDS (``eds``: every object hil uses, before anything is written),
        reach the drive by SDO and leave it in SWITCH ON DISABLED (voltage disabled), or in
        NOT READY TO SWITCH ON on its own way there (:meth:`enable` awaits it: some drives
        run their state machine only while process data flows).

        A drive found in FAULT is left alone (DriveFaultError): clearing a fault is an explicit
        decision, :meth:`recover`."""
        if self._closed:
            raise DriveError("the drive master is closed")
        if self.config.eds and self.description is None:  # before anything is written
            from hil.drivers.canopen.eds import load_description

            self.description = load_description(self.config.eds, self.node_id,
                                                 self.operation)
            self.objects.od = self.description.od
        self._latched, self._enabled = None, False
        self.heartbeat_watch.rebooted = False
        state = state_of(self.states.reach())
        if state in (FAULT, FAULT_REACTION_ACTIVE):
            code = self.objects.read(ERROR_CODE, 0, "<H")
            code = self.last_emcy_code if code is None else code
            raise DriveFaultError(f"drive node {self.node_id} is in {state} (error code "
                                  f"{emcy_text(code)}): clear it with `hil drive reset`, "
                                  "--reset-fault on a run, or recover()", code)
        if state not in (SWITCH_ON_DISABLED, NOT_READY_TO_SWITCH_ON):
            self.states.controlword(CW_DISABLE_VOLTAGE)  # left enabled by someone
            self.states.wait_state(SWITCH_ON_DISABLED, "disable voltage")
        self._check_mode()
        self.settings.open()  # an earlier run's leftover put back before the limits are read
        self._read_units_and_limits()

    def _read_units_and_limits(self) -> None:
        """The drive's scaling and its current limits (read only): what :meth:`configure`
        writes by, and the current a controller may be given before then."""
        if self._limit is not None:  # read once: 0x6072 may hold this master's own value since
            return
        c = self.config
        scaling, self._units_from = read_scaling(self.objects, c.increments_per_rev,
                                                 c.rated_current_ma)
        limit = read_current_limit(self.objects, scaling, c.current_limit_ma,
                                   c.max_torque_permille)
        stand_ins = {what: key for what, key in
                     [*self._units_from.items(), ("max_torque", limit.max_torque_from)]
                     if key.startswith("[master]")}
        if stand_ins:
            self._event("drive.stand_in", f"drive node {self.node_id} lacks objects: "
                        f"{', '.join(stand_ins.values())} stand in", stand_ins=stand_ins)
        unit = scaling.rated_current_ma / 1000.0
        if limit.applied_ma < unit:
            raise DriveError(f"drive node {self.node_id}: current limit {limit.text()}: below "
                             f"one torque unit of this drive ({unit:g} mA, per mille of its "
                             f"rated {scaling.rated_current_ma:g} mA): nothing could be sent")
        self.cyclic.scaling, self._limit = scaling, limit
        self._event("drive.current_limit", f"drive node {self.node_id}: current limit "
                    f"{limit.text()}", **limit.describe())

    def enable(self) -> None:
        """NMT start, then the controlwords to OPERATION ENABLED; ``feedback`` is then the
        drive's (:meth:`_enabled_feedback`). After :meth:`open` and :meth:`configure`."""
        self._enable()

    def _enable(self) -> Feedback:
        n = self.node_id
        self.nmt.command(NMT_START)
        try:
            self._enable_operation()
        except (DriveError, SdoAbortError):
            # the drive may have taken the controlwords whose answers were lost: its safe
            # state is asked for all the same (best effort: the link may be gone)
            with contextlib.suppress(DriveError, SdoAbortError):
                self.states.controlword(CW_DISABLE_VOLTAGE)
            raise
        self._enabled, self._lost_driving = True, False
        # watched from the first cycle on: a drive on the master's SYNC time (lockstep, or
        # an emulator's clock "sync") beats only once SYNCs come, however long the run took
        # between enabling it and its first tick
        self._watch_from_next_cycle = True
        feedback = self.cyclic.start(self._enabled_feedback())
        self._event("drive.enabled", f"drive node {n} OPERATION ENABLED at "
                    f"{feedback.position_deg:.4f} deg", position_deg=feedback.position_deg)
        return feedback

    def _enable_operation(self) -> None:
        """The controlwords to OPERATION ENABLED, each state awaited (on the master's
        :class:`~hil.drivers.canopen.state.StateWords`)."""
        self.states.enable()

    def _enabled_feedback(self) -> tuple[int, int, int, int] | None:
        """The enabled drive's first feedback (statusword, position, velocity, torque): read
        by SDO on CAN; None: the last cycle's answer."""
        read = self.sdo.read_int
        return (self.states.statusword(), read(POSITION_ACTUAL, 0, "<i"),
                self.objects.read(VELOCITY_ACTUAL, 0, "<i") or 0,
                self.objects.read(TORQUE_ACTUAL, 0, "<h") or 0)

    def start(self) -> Feedback:
        """:meth:`open`, :meth:`configure`, :meth:`enable`; return the drive's feedback."""
        self.open()
        self.configure()
        return self._enable()

    def fault_reset(self) -> None:
        """Leave a drive FAULT through the CiA 402 fault reset (the rising edge of controlword
        bit 7), after a fault reaction has ended; the drive is then in SWITCH ON DISABLED."""
        if self._closed:
            raise DriveError("the drive master is closed")
        if isinstance(self._latched, DriveLinkLostError):
            self.link.reconnect()
        self._latched = None
        self.heartbeat_watch.rebooted = False
        self.cyclic.drain()
        state = state_of(self.states.reach())
        if state == FAULT_REACTION_ACTIVE:  # braking: as long as a quick stop may take
            c = self.config
            self.states.wait_state(FAULT, "fault reaction",
                                   timeout_s=c.quick_stop_timeout_s + c.state_timeout_s)
            state = FAULT
        if state == FAULT:
            self.states.fault_reset()
            self._event("drive.fault_reset", f"drive node {self.node_id}: fault reset")

    def recover(self) -> Feedback:
        """Explicit recovery: reconnect if the link was lost, clear a drive FAULT, then
        :meth:`start` again."""
        self.fault_reset()
        return self.start()

    # -- the cyclic path ---------------------------------------------------------------------------
    def _check_latched(self) -> None:
        if self._latched is not None:
            error = copy.copy(self._latched)  # same type and data, a note on the message
            error.args = (f"{self._latched} (latched: call recover())",)
            raise error
        if not self._enabled:
            raise DriveStateError(f"drive node {self.node_id} is not enabled: call start()")

    def _send_cycle(self, controlword: int, target: int, command_ma: float = 0.0) -> None:
        if self._watch_from_next_cycle:
            self._watch_from_next_cycle = False
            self.heartbeat_watch.restart()
        try:
            self.cyclic.send(controlword, target, command_ma)
        except DriveLinkLostError as exc:
            self._lose_link(str(exc))

    def _receive(self, timeout_s: float | None = None, stopping: bool = False) -> Feedback:
        """The cycle's feedback (waiting at most ``timeout_s`` where given); a lost link raises.
        A refused queued download or another master on the bus raises too (latched), except in
        a safe stop (``stopping``), which goes on: the drive is stopped all the same."""
        cyclic, watch = self.cyclic, self.heartbeat_watch
        if not cyclic.awaiting:  # no cycle since the last read: the same feedback again
            return cyclic.receive()
        try:
            feedback = cyclic.receive(timeout_s)
        except DriveLinkLostError as exc:
            self._lose_link(str(exc), type(exc))
        if watch.rebooted:
            self._lose_link("the drive restarted (boot-up message)")
        # silent as of the feedback's time (the master's clock, read for it a moment ago)
        silent_ns = watch.silent_ns(feedback.t_ns) if self._enabled else None
        if silent_ns is not None:  # unless a heartbeat already here says otherwise: the frames
            try:                   # behind this cycle's TPDOs are read before the silence counts
                self.cyclic.drain()
            except DriveLinkLostError as exc:
                self._lose_link(str(exc))
            silent_ns = self.heartbeat_watch.silent_ns()
        if silent_ns is not None:
            self._lose_link(f"no heartbeat for {silent_ns / 1e6:.0f} ms (it beats every "
                            f"{self.config.drive_heartbeat_ms} ms)")
        if stopping:  # a stop goes on after another master or a refused write: only a lost
            return feedback  # link cuts it short
        error = self.sdo.take_error()
        if error is None and self.foreign is not None:
            error = BusSharedError(self.foreign)
        if error is not None and not stopping:
            self._latched = error
            raise error
        return feedback

    def _check_operation(self, feedback: Feedback) -> Feedback:
        state = feedback.state
        if state == OPERATION_ENABLED:
            self._operating_word = feedback.statusword
            return feedback
        if not feedback.fresh:
            return feedback
        n = self.node_id
        if state in (FAULT, FAULT_REACTION_ACTIVE):
            code = self.last_emcy_code
            error: DriveError = DriveFaultError(
                f"drive node {n} reports {state} (statusword 0x{feedback.statusword:04X}, last "
                f"EMCY {emcy_text(code)})", code)
            self._event("drive.fault", str(error), level="error", code=code)
            # its safe state asked for all the same: a drive in FAULT takes it as nothing,
            # one that only said so (a damaged TPDO) stops
            self.safe_state()
        else:
            error = DriveStateError(f"drive node {n} left OPERATION ENABLED: now {state} "
                                    f"(statusword 0x{feedback.statusword:04X})")
            self._event("drive.state", str(error), level="error", state=state)
            self.safe_state()
        self._latched = error
        raise error

    def _lose_link(self, reason: str, kind: type[DriveLinkLostError] = DriveLinkLostError
                   ) -> NoReturn:
        reason = reason.removeprefix(f"drive node {self.node_id}: ")
        error = kind(f"drive node {self.node_id} link lost: {reason}")
        self._latched = error
        self._event("drive.link_lost", str(error), level="error", cycle=self.cyclic.cycle)
        if self._enabled:  # best effort, without waiting: quick stop, then disable voltage
            self._enabled, self._lost_driving = False, True
            self.cyclic.send_now([CW_QUICK_STOP, CW_DISABLE_VOLTAGE])
        raise error

    @property
    def limit(self) -> CurrentLimit:
        """The current limit chain, as read at :meth:`open`."""
        if self._limit is None:
            raise DriveStateError(f"drive node {self.node_id}: its limits are read at open()")
        return self._limit

    @property
    def current_limit_ma(self) -> float:
        """What every command is clamped to: the smallest of the run's limit and the drive's
        0x6073 / 0x6072 (the run's alone before :meth:`open`)."""
        return self._limit.applied_ma if self._limit is not None \
            else self.config.current_limit_ma

    def tighten_current_limit(self, limit_ma: float) -> float:
        """Lower the run's current limit to ``limit_ma`` while running (never raised: a
        higher value is a DriveError); every later command is clamped to it. Returns the
        limit now applied [mA]."""
        if not 0 < limit_ma <= self.current_limit_ma:
            raise DriveError(f"drive node {self.node_id}: the current limit may only be "
                             f"lowered while running (now {self.current_limit_ma:g} mA, asked "
                             f"{limit_ma:g} mA)")
        if self._limit is None:
            self.config = replace(self.config, current_limit_ma=limit_ma)
        else:
            self._limit = replace(self._limit, run_ma=min(self._limit.run_ma, limit_ma))
        return self.current_limit_ma

    def applied_current(self, current_ma: float) -> float:
        """The current the drive is sent for a request of ``current_ma``: clamped to
        :attr:`current_limit_ma`."""
        limit = self.current_limit_ma
        low = -limit  # min(max(current_ma, low), limit), without two calls of a builtin
        above = low if low > current_ma else current_ma
        return limit if limit < above else above

    def send_set_point(self, value: float, bits: int = 0) -> None:
        """Send the mode's set point in its unit (a current [mA] in CST, clamped to the limit;
        a multi-turn position [deg] in CSP and PP; a velocity [deg/s] in CSV and PV; none in
        HM) and a SYNC; ``bits``: the mode's own controlword bits beside enable operation
        (:data:`~hil.protocols.cia402.CW_NEW_SET_POINT`, ``CW_HALT``...)."""
        if self._latched is not None or not self._enabled:
            self._check_latched()
        mode = self.operation
        if mode.unit == "mA":
            if not math.isfinite(value):
                raise DriveError(f"drive node {self.node_id}: refusing a non-finite current "
                                 f"command ({value!r})")
            clamped = self.applied_current(value)
            if clamped != value:
                self.stats.clamped_commands += 1
            self._send_cycle(CW_ENABLE_OPERATION | bits,
                             round(clamped * 1000.0 / self.cyclic.scaling.rated_current_ma),
                             clamped)
            return
        self._send_cycle(CW_ENABLE_OPERATION | bits, wire_value(
            mode, value, self.scaling, self.cyclic.turns, self.node_id), math.nan)

    def send_command(self, current_ma: float) -> None:
        """:meth:`send_set_point` of a current [mA] (CST)."""
        self._send_in("mA", current_ma, "send_command")

    def send_position(self, target_deg: float) -> None:
        """:meth:`send_set_point` of a position [deg, multi-turn] (CSP)."""
        self._send_in("deg", target_deg, "send_position")

    def _send_in(self, unit: str, value: float, name: str) -> None:
        if self.operation.unit != unit:
            raise DriveStateError(f"{name}() sends {unit}, and mode {self.operation.short} "
                                  f"takes {self.operation.unit or 'no set point'}: use "
                                  "send_set_point()")
        self.send_set_point(value)

    def receive_feedback(self) -> Feedback:
        """The TPDOs of the last SYNC (waits until ``rx_timeout`` after that SYNC); raises on
        fault or loss.

        Without a cycle sent since the last call it returns the last feedback again (the one
        of :meth:`start` before the first cycle)."""
        if self._latched is not None or not self._enabled:
            self._check_latched()
        feedback = self._receive()
        if feedback.statusword == self._operating_word:  # the state of the last good cycles
            return feedback
        return self._check_operation(feedback)

    def prime(self, timeout_s: float = PRIME_TIMEOUT_S) -> Feedback:
        """One cycle that holds the axis where it stands (no current, no velocity, or its
        position), its TPDOs waited for up to ``timeout_s`` rather than ``rx_timeout``: a
        real-time loop runs it before its clock starts, so that its first ticks do not pay
        for the first answer of a drive (or a process standing in for one) that has not
        answered a SYNC yet. Raises on fault or loss, as :meth:`receive_feedback` does."""
        self._check_latched()
        start = self.feedback
        target = holding_value(self.operation,
                               lambda: None if start is None else start.position_increments)
        self._send_cycle(CW_ENABLE_OPERATION, target)
        return self._check_operation(self._receive(timeout_s))

    def exchange(self, set_point: float) -> Feedback:
        """One cycle: the mode's set point (:meth:`send_set_point`), SYNC, feedback."""
        self.send_set_point(set_point)
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
        self._send_cycle(controlword, target)
        return self._receive()

    # -- stops ------------------------------------------------------------------------------------
    def safe_state(self) -> None:
        """Quick stop (cyclic, until standstill or the time-out), then disable voltage: the
        stop cycles below for this drive alone (:mod:`hil.drivers.canopen.stopping`, which an
        axis group runs for several drives in the same cycles).

        Idempotent and silent: failures become a ``drive.safe_stop_failed`` event."""
        stop_together([self])

    @property
    def enabled(self) -> bool:
        """Enabled by :meth:`start` and not stopped since (its safe stop is still to come)."""
        return self._enabled and not self._closed

    # The stop cycles, one drive's part of a safe stop: begin_stop(); then for each of
    # quick_stop_cycles() send_stop_cycle(CW_QUICK_STOP), receive_stop_cycle() and
    # report_stop_cycle() until the drive stands(); then one cycle of CW_DISABLE_VOLTAGE;
    # end_stop() with its feedback, or with the DriveError that cut the stop short.
    def begin_stop(self) -> bool:
        """Begin a safe stop: the cyclic run ends here (the drive counts as not enabled) and
        every stop cycle holds the target of this moment. False, and nothing to do, when the
        drive is not enabled (never started, or stopped already)."""
        if not self.enabled:
            return False
        self._enabled = False
        self._stop_target = self._holding_target()
        return True

    def _holding_target(self) -> int:
        """The raw set point that holds the axis where it last stood (its last feedback's
        position in a position mode; none read yet: 0x6064 by SDO)."""
        feedback = self.feedback
        return holding_value(self.operation, lambda: self.sdo.read_int(POSITION_ACTUAL, 0, "<i")
                             if feedback is None else feedback.position_increments)

    def quick_stop_cycles(self) -> Iterator[None]:
        """The quick-stop cycles of a safe stop: :meth:`periods` of the quick-stop
        time-out."""
        return self.periods(self.config.quick_stop_timeout_s)

    def periods(self, seconds: float) -> Iterator[None]:
        """Cycles one period apart on the master's clock (in lockstep each SYNC is a period):
        as many as ``seconds`` hold, at least one. Leave the loop when done; a cycle after the
        last waits its period."""
        c, clock = self.config, self.clock
        period_ns = round(c.cycle_period_s * 1e9)
        next_ns = clock.time_ns()
        for _ in range(max(1, math.ceil(seconds / c.cycle_period_s))):
            yield
            next_ns += period_ns
            wait_ns = next_ns - clock.time_ns()
            if wait_ns > 0:
                clock.sleep(wait_ns / 1e9)

    def send_stop_cycle(self, controlword: int) -> None:
        """Send one stop cycle's frames: ``controlword`` (``CW_QUICK_STOP`` or
        ``CW_DISABLE_VOLTAGE``) with the target held since :meth:`begin_stop`, and a SYNC (on
        an :class:`~hil.drivers.canopen.axes.AxisBus`, at its ``end_cycle``). Raises the error
        a lost link latched (another error that ended the run does not stop the stop)."""
        if isinstance(self._latched, DriveLinkLostError):
            self._check_latched()
        self._send_cycle(controlword, self._stop_target)

    def receive_stop_cycle(self) -> Feedback:
        """The drive's TPDOs of the stop cycle sent last; raises (:class:`DriveError`) when
        the link is lost."""
        return self._receive(stopping=True)

    def report_stop_cycle(self, feedback: Feedback) -> None:
        """Hand a stop cycle's feedback to ``on_stop_cycle``: one that raises is told no more
        (an event says so), and the stop goes on."""
        observer = self.on_stop_cycle
        if observer is None:
            return
        try:
            observer(feedback)
        except Exception as exc:
            self.on_stop_cycle = None
            self._event("drive.stop_observer_failed", f"drive node {self.node_id}: the stop's "
                        f"observer failed ({type(exc).__name__}: {exc}); the stop goes on",
                        level="warning")

    def stands(self, feedback: Feedback) -> bool:
        """Whether a quick-stop cycle's ``feedback`` ends the quick stop: fresh, and the drive
        in SWITCH ON DISABLED or FAULT, or in QUICK STOP ACTIVE below the standstill speed."""
        return feedback.fresh and (feedback.state in (SWITCH_ON_DISABLED, FAULT) or (
            feedback.state == QUICK_STOP_ACTIVE
            and abs(feedback.velocity_deg_s) < self.config.standstill_deg_s))

    def end_stop(self, outcome: Feedback | DriveError) -> None:
        """Tell how the safe stop ended: ``drive.safe_stop`` with the state of the disable
        voltage cycle's feedback; ``drive.safe_stop_failed`` when the drive ignored the stop
        (still OPERATION ENABLED) or a :class:`DriveError` cut it short."""
        n = self.node_id
        said, last = last_report(self.feedback)
        if isinstance(outcome, DriveError):
            self._event("drive.safe_stop_failed", f"drive node {n}: safe stop incomplete "
                        f"({outcome}); {said}: {MAY_STILL_MOVE}", level="error", last=last)
        elif outcome.state == OPERATION_ENABLED:  # it ignored both: only its SYNC watchdog is left
            self._event("drive.safe_stop_failed", f"drive node {n} ignored quick stop and "
                        f"disable voltage: {said}; no more SYNC, so its SYNC watchdog must "
                        f"fault it: {MAY_STILL_MOVE}", level="error", state=outcome.state,
                        last=last)
        else:
            self._event("drive.safe_stop", f"drive node {n} stopped: {outcome.state}",
                        state=outcome.state)

    def disconnect(self) -> None:
        """Release the bus and anything the master was built with (an emulator process);
        idempotent. :meth:`close` (safe stop, then this) is the usual way out. After a link
        lost while driving, the drive's state is confirmed first (:func:`confirm_stopped`)."""
        if self._closed:
            return
        reached = self._reach_again() if self._lost_driving or self.settings.log else False
        another = reached and self._another_drive()  # its own drive is not reached then
        if self._lost_driving:
            confirm_stopped(self.sdo, self.feedback, self._event, reached and not another)
        if self.settings.log and not another:
            self.settings.restore()  # those it cannot put back stay in the journal
        self._closed = True
        self._enabled = False
        self.link.shutdown()
        for closer in self._closers:
            closer()

    def _another_drive(self) -> bool:
        """After the link was reconnected: whether another drive than the one opened answers
        at the URL now (0x1018, :meth:`RunSettings.stranger`), which is then told and written
        nothing (its own run's settings, its state); this run's stay in the journal."""
        if self.link_up:
            return False
        try:
            stranger = self.settings.stranger()
        except DriveError:  # silent: the restore's time-out keeps the journal
            return False
        if stranger is None:
            return False
        opened = self.settings.identity.text() if self.settings.identity else "no identity"
        self._event("drive.not_the_drive_opened", f"drive node {self.node_id} at {self.url} is "
                    f"not the drive the run opened (0x1018: {stranger.text()}, opened: "
                    f"{opened}): nothing put back; the journal keeps it", level="warning",
                    identity=stranger.as_dict())
        return True

    def _reach_again(self) -> bool:
        """The link, reconnected after a lost one; False (and an event) when it cannot be."""
        if self.link_up:
            return True
        try:
            self.link.reconnect()
        except (DriveError, OSError) as exc:
            self._event("drive.reconnect_failed", f"drive node {self.node_id}: cannot reach it "
                        f"again after the lost link: {exc}", level="warning")
            return False
        return True
