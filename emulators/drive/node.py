"""A CiA 402 servo drive emulated on a CAN bus: the node that composes its parts and
dispatches frames to them.

The node is transport-agnostic: frames (:data:`~hil.protocols.can_frames.Frame`, ``(id, data)``)
come in through :meth:`DriveNode.handle_frame` (:meth:`DriveNode.handle` for a python-can
message), time-driven work (heartbeat production, watchdogs, ramp time-outs) runs in
:meth:`DriveNode.service`, and frames go out through a ``send(list_of_frames)`` callable
(:mod:`hil.emulators.drive.runners` runs it on a bus, or in lockstep).

Its dictionary is hil's own or a twin of a real drive's EDS (:mod:`~hil.emulators.drive.twin`:
its objects, PDO maps, axis units and modes). Its parts, one job each:
:mod:`~hil.emulators.drive.objects` (dictionary and live values),
:mod:`~hil.emulators.drive.sdo` (the SDO server), :mod:`~hil.emulators.drive.pdo` (PDOs),
:mod:`~hil.emulators.drive.states` (the CiA 402 state machine), :mod:`~hil.emulators.drive.motor`
(the current loops, each mode's motion by the mode table: :mod:`~hil.emulators.drive.modes`),
:mod:`~hil.emulators.drive.switches` (limit and home switches, index pulse: 0x60FD) and
:mod:`~hil.emulators.drive.plant` (the axis). The node itself is NMT,
heartbeats, SYNC, EMCY, what writing an object means, and faults on purpose.

Cyclic path (raw frames, never the ``canopen`` PDO machinery): an RPDO is stored on reception;
on SYNC the node latches it (controlword and targets), advances the plant one communication
cycle (0x1006 / plant period steps, at least one), and sends the TPDOs whose transmission type
counter expires; event-driven TPDOs go out from :meth:`DriveNode.service` when their data
change. Every value an SDO reads is the one the last TPDO carried.

Faults: heartbeat-consumer time-out or SYNC loss while the power stage is enabled -> EMCY
0x8130; commanded current above the trip level -> EMCY 0x2310; either starts the fault reaction
(brake to standstill, at most the quick-stop time-out) then FAULT with torque off. A fault reset
is the rising edge of controlword bit 7. Malformed frames never raise: SDO aborts with the CiA 301
code, PDO length errors and bad SYNC lengths give EMCY 0x8210 / 0x8220 / 0x8240. Leaving NMT
OPERATIONAL with the power stage on loses the cyclic commands: EMCY 0x8100 and fault.

Simplifications, on purpose: the plant moves only on SYNC, also during a quick stop or fault
reaction (without SYNC these end by their time-out, or at once when the axis already stands);
braking is the drive's velocity loop at the current limit; quick-stop options 5/6 then hold with
zero current; the modes' loops (CSP, PP, HM: a position P loop with velocity feed-forward around
a velocity P loop; CSV, PV: the velocity loop) run once per SYNC, tuned for a 500 us cycle.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Iterable
from functools import partial

import can

from hil.contracts import PollBudget
from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.motor import MotorLoops
from hil.emulators.drive.pdo import Pdo, PdoTable
from hil.emulators.drive.plant import AxisPlant
from hil.emulators.drive.sdo import SdoServer
from hil.emulators.drive.states import POWERED, DriveStates
from hil.emulators.drive.timebase import CLOCKS, TIME_BASE
from hil.emulators.drive.twin import drive_dictionary
from hil.emulators.faults import Fault, FaultSchedule, for_emulator
from hil.protocols.can_frames import Frame, from_message
from hil.protocols.cia301 import (
    ABORT_DEVICE_STATE,
    ABORT_VALUE,
    ABORT_VALUE_HIGH,
    CONSUMER_HEARTBEAT,
    CYCLE_PERIOD,
    EMCY_BASE,
    EMCY_COMMUNICATION,
    EMCY_HEARTBEAT,
    EMCY_RESET,
    EMCY_SOFTWARE,
    EMCY_SYNC_LENGTH,
    ERR_REG_COMMUNICATION,
    ERR_REG_GENERIC,
    ERROR_REGISTER,
    HEARTBEAT_BASE,
    MAX_NODE_ID,
    NMT_BOOT_UP,
    NMT_COB_ID,
    NMT_ENTER_PRE_OPERATIONAL,
    NMT_OPERATIONAL,
    NMT_PRE_OPERATIONAL,
    NMT_RESET_COMMUNICATION,
    NMT_RESET_NODE,
    NMT_START,
    NMT_STOP,
    NMT_STOPPED,
    PRODUCER_HEARTBEAT,
    SDO_REQUEST_BASE,
    SDO_RESPONSE_BASE,
    SYNC_COB_ID_OBJECT,
    SYNC_COUNTER_OVERFLOW,
    SdoAbortError,
    error_register_bit,
)
from hil.protocols.cia402 import (
    CONTROLWORD,
    DIGITAL_INPUTS,
    FAULT,
    HOMING_METHOD,
    HOMING_METHODS,
    MODES_DISPLAY,
    MODES_OF_OPERATION,
    OPERATION_ENABLED,
    POSITION_ACTUAL,
    POSITION_DEMAND,
    QUICK_STOP_ACTIVE,
    QUICK_STOP_OPTION,
    QUICK_STOP_OPTIONS,
    RATED_CURRENT,
    STATUSWORD,
    SWITCH_ON_DISABLED,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
    VELOCITY_DEMAND,
)

log = logging.getLogger(__name__)

SYNC_LOSS_TIMEOUT = 0x2001  # [ms] (manufacturer object)
DISTURBANCE = 0x2003        # external disturbance torque [mA] (manufacturer object)
SYNC_ECHO = 0x2004          # the counter of the SYNC the TPDOs answer (manufacturer object)
SYNC_POLL_PERIODS = 100     # SYNCs are expected until this many cycles passed without one
#: the most plant steps one SYNC may take (10 s of the published axis' 500 us): a longer
#: communication cycle (0x1006) is refused, not stepped for minutes under the node's lock
MAX_STEPS_PER_SYNC = 20_000
#: on a lockstep master's time the next SYNC is expected for this long after the last frame
LOCKSTEP_POLL_NS = 1_000_000
# manufacturer byte 3 of an EMCY 0x8130: which watchdog fired
CAUSE_HEARTBEAT, CAUSE_SYNC = 0x01, 0x02
EXTENDED_OR_PRODUCER = 0x6000_0000  # COB-ID SYNC: bit 30 (we would produce), bit 29 (29-bit)
NODE_ID_MASK = 0xFF80_0000           # consumer heartbeat: bits above the node id
PDO_IDS_FIRST, PDO_IDS_LAST = 0x180, 0x57F  # the default PDO COB-IDs of every node

# the objects the cyclic path reads and writes, as keys of the value store
CONTROLWORD_KEY, MODE_KEY = (CONTROLWORD, 0), (MODES_OF_OPERATION, 0)
POSITION_KEY, VELOCITY_KEY = (POSITION_ACTUAL, 0), (VELOCITY_ACTUAL, 0)
TORQUE_KEY, STATUSWORD_KEY, RATED_KEY = (TORQUE_ACTUAL, 0), (STATUSWORD, 0), (RATED_CURRENT, 0)
SYNC_OVERFLOW_KEY, SYNC_ECHO_KEY = (SYNC_COUNTER_OVERFLOW, 0), (SYNC_ECHO, 0)
DEMAND_POSITION_KEY, DEMAND_VELOCITY_KEY = (POSITION_DEMAND, 0), (VELOCITY_DEMAND, 0)
INPUTS_KEY = (DIGITAL_INPUTS, 0)
NO_HOMING = 0  # 0x6098 = 0: no homing method


#: the actual values a drive refreshes each cycle, in the order :func:`wire_actuals` gives them
ACTUAL_KEYS = (POSITION_KEY, DEMAND_POSITION_KEY, DEMAND_VELOCITY_KEY, INPUTS_KEY, VELOCITY_KEY,
               TORQUE_KEY, STATUSWORD_KEY)


def wire_actuals(position_deg: float, velocity_deg_s: float, per_turn: int, offset: int,
                 demand: tuple[float, float], inputs: int, applied_ma: float, rated_ma: int,
                 statusword: int) -> tuple[int, ...]:
    """The :data:`ACTUAL_KEYS` as the drive's objects hold them: the position modulo one turn
    (0x6064), the demand position and velocity [increments, increments/s] wrapped into
    INTEGER32 as a drive's counter wraps (0x6062, 0x606B), the inputs (0x60FD), the velocity
    and the torque clamped to INTEGER32 and INTEGER16 (0x606C, 0x6077 in per mille of the
    rated current), the statusword. A value that is not finite raises (ValueError,
    OverflowError)."""
    velocity = round(velocity_deg_s / 360.0 * per_turn)
    torque = round(applied_ma * 1000.0 / rated_ma)
    demand_position, demand_velocity = demand
    return ((math.floor(position_deg / 360.0 * per_turn) + offset) % per_turn,
            (math.floor(demand_position) + 2**31) % 2**32 - 2**31,
            (round(demand_velocity) + 2**31) % 2**32 - 2**31,
            inputs,
            -(2**31) if velocity < -(2**31) else 2**31 - 1 if velocity > 2**31 - 1 else velocity,
            -32768 if torque < -32768 else 32767 if torque > 32767 else torque,
            statusword)


SendFn = Callable[[list[Frame]], None]
# what writing an object means beyond storing its value: (index, subindex, value), raises
# SdoAbortError with the CiA code to refuse it
WriteEffect = Callable[[int, int, int], None]
FrameHandler = Callable[[bytes], None]  # what a received frame means, given its data


class DriveNode:
    """The emulated drive. :meth:`handle`, :meth:`service` and :meth:`boot` hold ``lock``, so
    a runner may call them from different threads."""

    def __init__(
        self,
        config: DriveEmulatorConfig | None = None,
        *,
        send: SendFn,
        plant: AxisPlant | None = None,
        clock: str = "auto",
        faults: Iterable[Fault] = (),
        on_fault: Callable[[str], None] | None = None,
    ) -> None:
        if clock not in CLOCKS:
            raise ValueError(f"clock must be one of {', '.join(CLOCKS)}, got {clock!r}")
        config = config or DriveEmulatorConfig()
        self.dictionary = drive_dictionary(config)  # hil's own, or the twin of config.eds
        self.config = config = self.dictionary.configure(config)
        self._switches = config.switches
        self.node_id = config.node_id
        self.plant = plant if plant is not None else config.make_plant()
        self.object_dictionary = self.dictionary.od
        self.objects = self.dictionary.store()
        self._values = self.objects.values
        self.lock = threading.RLock()
        self._send_fn = send
        # time: the wall clock, or the SYNCs so far (a lockstep master's time, from
        # _sync_origin_ns on); "auto" follows what a master asks for in 0x2005
        self.clock = clock
        self._sync_timebase = clock == "sync"
        self._sync_origin_ns = 0
        self._gone_after_ns = 0     # SYNC time given up after this much wall time unheard
        self._heard_ns = time.monotonic_ns()  # wall time of the last frame
        self._sync_poll = PollBudget(LOCKSTEP_POLL_NS)  # the wait for a lockstep master's SYNC
        self._poll_from_ns = 0  # the frame that wait started from
        self._hb_next_ns: int | None = None     # when the next heartbeat is due
        self._plant_period_ns = round(self.plant.dt * 1e9)
        sdo_response_id = SDO_RESPONSE_BASE + self.node_id
        self.sdo = SdoServer(self.objects.read, self._download,
                             lambda data: self._send([(sdo_response_id, data)]))
        self.pdos = PdoTable(self.objects)
        # the frames served in every NMT state, by COB-ID: NMT commands, every node's heartbeat;
        # outside STOPPED also those of _served_unless_stopped, and the RPDOs
        self._always_served: dict[int, FrameHandler] = {
            NMT_COB_ID: self._on_nmt,
            **{HEARTBEAT_BASE + node: partial(self._on_heartbeat, node)
               for node in range(MAX_NODE_ID + 1)},
        }
        self._served_unless_stopped: dict[int, FrameHandler] = {}  # SYNC, SDO: _listen_to_sync
        # all three in one table outside STOPPED (rebuilt when the RPDOs or the SYNC change)
        self._served: dict[int, FrameHandler] = {}
        self._served_receivers: dict[int, Pdo] | None = None  # the RPDOs it was built for
        # what each NMT command does
        self._nmt_commands: dict[int, Callable[[], None]] = {
            NMT_START: partial(self._set_nmt, NMT_OPERATIONAL),
            NMT_STOP: partial(self._set_nmt, NMT_STOPPED),
            NMT_ENTER_PRE_OPERATIONAL: partial(self._set_nmt, NMT_PRE_OPERATIONAL),
            NMT_RESET_NODE: self._reset_node,
            NMT_RESET_COMMUNICATION: self._reset_communication,
        }
        # the objects whose writing means more than storing the value, and what it means: the
        # one list of them (:meth:`_write`)
        self._write_effects: dict[int, WriteEffect] = {
            **{index: partial(self._write_pdo, pdo) for index, pdo in self.pdos.by_object.items()},
            SYNC_COB_ID_OBJECT: self._write_sync_cob_id,
            SYNC_COUNTER_OVERFLOW: self._write_sync_counter_overflow,
            CYCLE_PERIOD: self._write_cycle_period,
            CONSUMER_HEARTBEAT: self._write_consumer_heartbeat,
            PRODUCER_HEARTBEAT: self._write_producer_heartbeat,
            QUICK_STOP_OPTION: self._write_quick_stop_option,
            MODES_OF_OPERATION: self._write_mode,
            HOMING_METHOD: self._write_homing_method,
            CONTROLWORD: lambda _index, _subindex, value: self._apply_controlword(value),
            DISTURBANCE: self._write_disturbance,
            TIME_BASE: self._write_time_base,
        }
        self.states = DriveStates(self._values, self.plant, config.standstill_deg_s, self._now,
                                  self._emcy, self._entered)
        self.motor = MotorLoops(self._values, self.plant, config, self.states)
        self.sync_count = 0
        self._sync_time_ns = 0
        self.internal_errors = 0
        self.nmt_state = NMT_BOOT_UP
        self._t0_ns = self._now()
        #: the faults played, in seconds of the node's time since it was created
        self.faults = FaultSchedule(for_emulator(faults, "drive"),
                                    lambda: (self._now() - self._t0_ns) / 1e9, on_fault)
        self._fault_list = self.faults.faults  # empty: no fault to look for on the cyclic path
        self._delayed: list[tuple[int, list[Frame]]] = []
        self._serviced = False  # the time service ran after the frame just dispatched
        #: told whenever :meth:`hears` may answer differently (a bus's acceptance filter)
        self.on_hearing_changed: Callable[[], None] | None = None
        self._reset_application()

    # ---------------------------------------------------------------- life cycle and time
    @property
    def state(self) -> str:
        """The CiA 402 state."""
        return self.states.state

    @property
    def statusword(self) -> int:
        return self.states.statusword

    @property
    def sync_time_ns(self) -> int:
        """The time its SYNCs have made: one communication cycle each."""
        return self._sync_time_ns

    @property
    def cycle_period_ns(self) -> int:
        """The communication cycle: 0x1006, or the plant's period before it is set."""
        return self._steps_per_sync * self._plant_period_ns

    def _now(self) -> int:
        if self._sync_timebase:
            return self._sync_origin_ns + self._sync_time_ns
        return time.monotonic_ns()

    @property
    def on_master_time(self) -> bool:
        """Whether the node's time is the master's SYNCs (lockstep) rather than its own."""
        return self._sync_timebase

    def _take_master_time(self, bound_ms: int) -> None:
        """0x2005 = N: from now on time is the master's SYNCs (continuing from the time it
        is now), given up after ``bound_ms`` of wall time with no frame at all; 0: own clock."""
        if self.clock == "wall" and bound_ms:
            raise SdoAbortError(ABORT_DEVICE_STATE)  # keeps its own clock: the master is told
        if self.clock == "sync" and not bound_ms:
            raise SdoAbortError(ABORT_DEVICE_STATE)  # on SYNC time from power-on, for good
        if bound_ms and not self._sync_timebase:
            self._sync_origin_ns = time.monotonic_ns() - self._sync_time_ns
            self._sync_timebase = True
        elif not bound_ms and self._sync_timebase:
            self._own_clock_again()
        self._gone_after_ns = bound_ms * 1_000_000

    def _own_clock_again(self) -> None:
        """Back on the wall clock: every timer starts afresh from now."""
        self._sync_timebase = False
        self._gone_after_ns = 0
        now = time.monotonic_ns()
        self._hb_next_ns = None
        self._hb_last_ns = self._sync_last_ns = now

    def _reset_application(self) -> None:
        """Power-on / NMT reset node: parameters to defaults, state machine restarted (and,
        ``auto``, the drive's own clock again)."""
        if self.clock == "auto" and self._sync_timebase:
            self._own_clock_again()
        self.objects.reset()
        self.states.reset()
        self.motor.reset()
        self.pdos.pending.clear()
        self.plant.extra_disturbance_ma = 0.0
        self._reset_communication_state()
        self._refresh_actuals()

    def _reset_communication_state(self) -> None:
        self.pdos.compile_all()
        self._listen_to_sync(self._values[(SYNC_COB_ID_OBJECT, 0)] & 0x7FF)
        self._steps_per_sync = self._steps_for_period(self._values[(CYCLE_PERIOD, 0)])
        self._hb_next_ns = None
        self._hb_consumer_armed = False
        self._hb_last_ns = 0
        self._sync_armed = False
        self._sync_last_ns = 0

    def _listen_to_sync(self, cob_id: int) -> None:
        """SYNC from now on is the frame with ``cob_id`` (0x1005): served ahead of an SDO
        request with the same COB-ID."""
        self._sync_cob_id = cob_id
        self._served_unless_stopped = {SDO_REQUEST_BASE + self.node_id: self.sdo.handle,
                                       cob_id: self._on_sync}
        self._served_receivers = None  # the table of what it serves, afresh
        self._hearing_changed()

    def hears(self, can_id: int) -> bool:
        """Whether a frame with ``can_id`` may mean anything to the node: every one but a PDO
        that is neither its SYNC nor one of its valid RPDOs (another node's)."""
        return not PDO_IDS_FIRST <= can_id <= PDO_IDS_LAST or can_id == self._sync_cob_id \
            or can_id in self.pdos.receivers

    def _hearing_changed(self) -> None:
        if self.on_hearing_changed is not None:
            self.on_hearing_changed()

    def next_sync_ns(self, now_ns: int) -> int | None:
        """When the next SYNC is due, on the grid of the communication cycle (0x1006) from the
        last one received (the slot after, once half a period has passed without it); None
        when no cyclic SYNC is going on. A real-time runner polls the bus around that time:
        a real drive answers a SYNC within microseconds, a process woken up from a blocking
        wait may take hundreds. On a lockstep master's time the next SYNC comes as soon as the
        master has done its tick: it is due at once until :data:`LOCKSTEP_POLL_NS` of wall
        time passed since the last frame (then the master is busy elsewhere, and a blocking
        wait costs the run nothing), while polling pays (:class:`~hil.contracts.PollBudget`:
        not on a machine too busy to leave the poller its core). ``now_ns``: the monotonic
        clock."""
        if self._sync_timebase:
            if self._heard_ns != self._poll_from_ns:  # a frame came: a new wait begins
                self._poll_from_ns = self._heard_ns
                self._sync_poll.start(now_ns)
            return now_ns if self._sync_poll.polling(now_ns) else None
        period_ns = self._values[(CYCLE_PERIOD, 0)] * 1000
        last = self._sync_last_ns
        if not period_ns or not last or now_ns - last > SYNC_POLL_PERIODS * period_ns:
            return None
        late = now_ns - last - period_ns - period_ns // 2
        return last + period_ns * (1 + max(0, late // period_ns + 1))

    def boot(self) -> None:
        """Power on: NOT READY TO SWITCH ON -> SWITCH ON DISABLED, boot-up message, PRE-OP."""
        with self.lock:
            self.states.enter(SWITCH_ON_DISABLED)
            self._enter_pre_operational_after_boot()

    def _enter_pre_operational_after_boot(self) -> None:
        self.nmt_state = NMT_BOOT_UP
        self._send([(HEARTBEAT_BASE + self.node_id, bytes([NMT_BOOT_UP]))])  # boot-up
        self.nmt_state = NMT_PRE_OPERATIONAL
        self._hb_next_ns = None

    def _entered(self, state: str) -> None:
        """What a change of CiA 402 state means beyond the state machine."""
        self.motor.forget()  # CSP feed-forward starts afresh
        if state not in POWERED:
            self._sync_armed = False
        self._refresh_actuals()

    # ---------------------------------------------------------------------- transport
    def _send(self, frames: list[Frame]) -> None:
        if self._fault_list:
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
        self.handle_frames(((can_id, data),))

    def handle_frames(self, frames: Iterable[Frame], heard_ns: int | None = None) -> bool:
        """Process received 11-bit data frames in their order, the lock taken once (a
        lockstep runner hands over all that came in one transmission, heard at ``heard_ns``
        of the monotonic clock: now by default); never raises.
        Returns whether the time service ran after the last of them (its SYNC's, on the
        master's time): a runner need not run it again before time moves on."""
        self._heard_ns = time.monotonic_ns() if heard_ns is None else heard_ns
        pdos = self.pdos
        serviced = False
        with self.lock:
            for can_id, data in frames:
                if PDO_IDS_FIRST <= can_id <= PDO_IDS_LAST and can_id != self._sync_cob_id \
                        and can_id not in pdos.receivers:
                    continue  # another node's PDO (drives on a bus hear each other's): nothing
                if self._fault_list and self.faults.active("silent"):
                    return False  # bus-off: it hears nothing either
                self._serviced = False
                try:
                    self._dispatch(can_id, data)
                except Exception:  # a bug must not take the drive down: report it as an EMCY
                    self.internal_errors += 1
                    log.exception("drive node %d: internal error on frame 0x%03X %s",
                                  self.node_id, can_id, data.hex())
                    self._emcy(EMCY_SOFTWARE, ERR_REG_GENERIC)
                serviced = self._serviced
        return serviced

    def hear(self, heard_ns: int) -> None:
        """A frame was on the bus at ``heard_ns`` (monotonic), though none for this node
        (a bus's acceptance filter took it away): the master is there."""
        self._heard_ns = heard_ns

    def _dispatch(self, can_id: int, data: bytes) -> None:
        if self.nmt_state == NMT_STOPPED:
            handler = self._always_served.get(can_id)  # NMT and heartbeats alone
        else:
            if self.pdos.receivers is not self._served_receivers:
                self._serve()
            handler = self._served.get(can_id)
        if handler is not None:
            handler(data)

    def _serve(self) -> None:
        """The table of what it serves outside STOPPED, for the RPDOs it has now: NMT and
        heartbeats first, then SYNC (ahead of an SDO request with its COB-ID), then RPDOs."""
        receivers = self.pdos.receivers
        self._served_receivers = receivers
        rpdos = {cob_id: partial(self._on_rpdo, pdo) for cob_id, pdo in receivers.items()}
        self._served = {**rpdos, **self._served_unless_stopped, **self._always_served}

    # ------------------------------------------------ the drive for another transport's skin
    # An EtherCAT slave (:mod:`hil.emulators.ethercat`) reaches the same drive through these:
    # its mailbox's SDO, its AL state, its process-data cycles; no CAN frame is involved.
    def upload(self, index: int, subindex: int) -> bytes:
        """An object's value as an SDO upload reads it; raises SdoAbortError."""
        with self.lock:
            self._heard_ns = time.monotonic_ns()
            return self.objects.read(index, subindex)

    def download(self, index: int, subindex: int, data: bytes) -> None:
        """An SDO download, with what writing the object means; raises SdoAbortError."""
        with self.lock:
            self._heard_ns = time.monotonic_ns()
            self._download(index, subindex, data)

    def store(self, index: int, subindex: int, data: bytes) -> None:
        """An SDO download stored, without what writing the object means (one the process
        data writes every cycle: the next cycle's value is the one that counts)."""
        with self.lock:
            self._heard_ns = time.monotonic_ns()
            self._values[(index, subindex)] = self.objects.decode_download(index, subindex, data)

    def set_operational(self, operational: bool) -> None:
        """Process data on (the outputs applied each cycle: NMT OPERATIONAL) or off
        (PRE-OPERATIONAL): leaving it with the power stage on faults the drive."""
        with self.lock:
            self._set_nmt(NMT_OPERATIONAL if operational else NMT_PRE_OPERATIONAL)

    def process_data_cycle(self, received: list[tuple[Pdo, bytes]]) -> None:
        """One process-data cycle: ``received`` (each RPDO's data) applied when operational,
        the plant advanced one period, then what falls due at the new time; never raises."""
        with self.lock:
            self._heard_ns = time.monotonic_ns()
            try:
                operational = self.nmt_state == NMT_OPERATIONAL
                self._advance_cycle(received if operational else [])
                if self._sync_timebase:
                    self._service(self._now())
            except Exception:
                self.internal_errors += 1
                log.exception("drive node %d: internal error in a process-data cycle",
                              self.node_id)
                self._emcy(EMCY_SOFTWARE, ERR_REG_GENERIC)

    def pdo_data(self, pdo: Pdo) -> bytes:
        """A TPDO's data now (its mapped objects' values)."""
        with self.lock:
            return self.pdos.data(pdo)

    # ------------------------------------------------------------------------------ NMT
    def _on_nmt(self, data: bytes) -> None:
        if len(data) != 2 or data[1] not in (0, self.node_id):
            return
        command = self._nmt_commands.get(data[0])
        if command is not None:
            command()

    def _reset_node(self) -> None:
        """NMT reset node: application and communication."""
        self._reset_application()
        self.states.enter(SWITCH_ON_DISABLED)
        self._enter_pre_operational_after_boot()

    def _reset_communication(self) -> None:
        """NMT reset communication: the communication objects (below 0x2000) to defaults."""
        self._leave_operational_check()
        self.objects.reset(lambda var: var.index < 0x2000)
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
            self.pdos.restart()

    def _leave_operational_check(self) -> None:
        """Leaving OPERATIONAL with the power stage on loses the cyclic commands: fault."""
        if self.nmt_state == NMT_OPERATIONAL and self.state in (OPERATION_ENABLED,
                                                                QUICK_STOP_ACTIVE):
            self.states.fault(EMCY_COMMUNICATION, ERR_REG_COMMUNICATION)

    # ------------------------------------------------------------------------- heartbeat
    def _on_heartbeat(self, producer: int, data: bytes) -> None:
        consumer = self._values[(CONSUMER_HEARTBEAT, 1)]
        watched, timeout_ms = (consumer >> 16) & 0x7F, consumer & 0xFFFF
        if len(data) < 1 or producer != watched or not watched or not timeout_ms:
            return
        self._hb_last_ns = self._now()
        self._hb_consumer_armed = True
        if self.states.comm_warning and self.state != FAULT:  # the lost master is back
            self.states.comm_warning = False
            self._values[(ERROR_REGISTER, 0)] &= ~(ERR_REG_COMMUNICATION | ERR_REG_GENERIC)
            self._emcy(EMCY_RESET, 0)

    # ------------------------------------------------------------- object write effects
    def _download(self, index: int, subindex: int, data: bytes) -> None:
        """An SDO download: checked by the store, then what writing it means."""
        self._write(index, subindex, self.objects.decode_download(index, subindex, data))

    def _write(self, index: int, subindex: int, value: int) -> None:
        """Validate and apply one write (SDO or RPDO): its effect (``_write_effects``), or
        else the value stored; raises SdoAbortError with the CiA code."""
        effect = self._write_effects.get(index)
        if effect is None:  # a plain value
            self._values[(index, subindex)] = value
        else:
            effect(index, subindex, value)

    def _write_pdo(self, pdo: Pdo, index: int, subindex: int, value: int) -> None:
        """A PDO's communication or mapping object: the RPDOs it hears may change."""
        try:
            self.pdos.write(pdo, index, subindex, value)
        finally:
            self._hearing_changed()

    def _write_sync_cob_id(self, index: int, subindex: int, value: int) -> None:
        if value & EXTENDED_OR_PRODUCER or value & 0x7FF == 0:  # we do not produce SYNC
            raise SdoAbortError(ABORT_VALUE)
        self._values[(index, subindex)] = value
        self._listen_to_sync(value & 0x7FF)

    def _write_sync_counter_overflow(self, index: int, subindex: int, value: int) -> None:
        if self._values[(CYCLE_PERIOD, 0)] != 0 or value == 1:  # CiA 301: only while 0x1006 = 0
            raise SdoAbortError(ABORT_DEVICE_STATE if value != 1 else ABORT_VALUE)
        self._values[(index, subindex)] = value

    def _write_cycle_period(self, index: int, subindex: int, value: int) -> None:
        steps = self._steps_for_period(value)
        self._values[(index, subindex)] = value
        self._steps_per_sync = steps

    def _write_consumer_heartbeat(self, index: int, subindex: int, value: int) -> None:
        if value & NODE_ID_MASK or (value >> 16) == self.node_id:
            raise SdoAbortError(ABORT_VALUE)
        self._values[(index, subindex)] = value
        self._hb_consumer_armed = False

    def _write_producer_heartbeat(self, index: int, subindex: int, value: int) -> None:
        self._values[(index, subindex)] = value
        self._hb_next_ns = None

    def _write_quick_stop_option(self, index: int, subindex: int, value: int) -> None:
        if value not in QUICK_STOP_OPTIONS:
            raise SdoAbortError(ABORT_VALUE)
        self._values[(index, subindex)] = value

    def _write_mode(self, index: int, subindex: int, value: int) -> None:
        self.dictionary.check_mode(value)  # the modes it emulates (of those 0x6502 lists)
        changed = value != self._values[(MODES_DISPLAY, 0)]
        self._values[(index, subindex)] = value
        self._values[(MODES_DISPLAY, 0)] = value
        if changed:  # the new mode's motion starts from where the axis is
            self.motor.forget()

    def _write_homing_method(self, index: int, subindex: int, value: int) -> None:
        if value not in HOMING_METHODS and value != NO_HOMING:
            raise SdoAbortError(ABORT_VALUE)
        self._values[(index, subindex)] = value

    def _write_disturbance(self, index: int, subindex: int, value: int) -> None:
        self._values[(index, subindex)] = value
        self.plant.extra_disturbance_ma = float(value)

    def _write_time_base(self, index: int, subindex: int, value: int) -> None:
        self._take_master_time(value)
        self._values[(index, subindex)] = value

    def _steps_for_period(self, period_us: int) -> int:
        """Plant steps per SYNC for a communication cycle period (0 = not set: one step); a
        period that is no multiple of the plant's, or longer than
        :data:`MAX_STEPS_PER_SYNC` steps, is refused (SdoAbortError)."""
        if period_us == 0:
            return 1
        period_ns = period_us * 1000
        if period_ns % self._plant_period_ns:
            raise SdoAbortError(ABORT_VALUE)
        if period_ns // self._plant_period_ns > MAX_STEPS_PER_SYNC:
            raise SdoAbortError(ABORT_VALUE_HIGH)
        return period_ns // self._plant_period_ns

    def _apply_controlword(self, cw: int) -> None:
        if self._fault_list:
            for fault in self.faults.active("ignore_controlword"):
                self.faults.hit(fault)
                return
        previous = self.states.controlword
        self.states.apply_controlword(cw)
        self.motor.controlword(cw, previous)
        self._values[STATUSWORD_KEY] = self.states.statusword  # the mode's bits too

    # ------------------------------------------------------------------------------ PDOs
    def _on_rpdo(self, pdo: Pdo, data: bytes) -> None:
        if self.nmt_state != NMT_OPERATIONAL:
            return
        now, emcy = self.pdos.receive(pdo, data)
        if emcy:
            self._emcy(emcy, ERR_REG_COMMUNICATION, raise_register=False)
        if now is not None:
            self._apply_rpdo(pdo, now)

    def _apply_rpdo(self, pdo: Pdo, data: bytes) -> None:
        controlword = None
        values, effects = self._values, self._write_effects
        for key, value in zip(pdo.keys, pdo.layout.unpack(data), strict=True):
            if key == CONTROLWORD_KEY:
                controlword = value  # applied after the targets of the same PDO
            elif key[0] not in effects:
                values[key] = value  # a plain value (:meth:`_write`)
            elif key == MODE_KEY and value not in self.dictionary.modes:
                continue  # invalid mode in a PDO: ignored, the display keeps the active mode
            else:
                try:
                    self._write(key[0], key[1], value)
                except SdoAbortError:
                    continue  # a value the object refuses: ignored like an invalid mode
        if controlword is not None:
            self._apply_controlword(controlword)

    def _send_tpdos(self) -> None:
        frames = self.pdos.tpdo_frames()
        if frames and self._fault_list:
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
        self._sync_cycle(data)
        if self._sync_timebase:  # time moved on: what is due now, in the SYNC's order
            self._service(self._sync_origin_ns + self._sync_time_ns)  # its _now()
            self._serviced = True

    def _sync_cycle(self, data: bytes) -> None:
        if len(data) > 1:
            self._emcy(EMCY_SYNC_LENGTH, ERR_REG_COMMUNICATION, raise_register=False)
            return
        if data and self._values[SYNC_OVERFLOW_KEY]:  # the SYNC counter is on
            self._values[SYNC_ECHO_KEY] = data[0]
        operational = self.nmt_state == NMT_OPERATIONAL
        self._advance_cycle(self.pdos.latched() if operational and self.pdos.pending else [])
        if operational:
            self._send_tpdos()

    def _advance_cycle(self, received: list[tuple[Pdo, bytes]]) -> None:
        """One communication cycle: ``received`` RPDO data applied, the plant advanced one
        period, the cycle's time counted (a SYNC's, or another transport's process-data
        cycle)."""
        for pdo, data in received:
            self._apply_rpdo(pdo, data)
        self._advance_plant()
        self.sync_count += 1
        self._sync_time_ns += self._steps_per_sync * self._plant_period_ns
        self._sync_last_ns = self._now()
        self._sync_armed = self.nmt_state == NMT_OPERATIONAL and \
            self.states.state in (OPERATION_ENABLED, QUICK_STOP_ACTIVE)

    def _advance_plant(self) -> None:
        states = self.states
        current, states.limit_active = self.motor.current(self._steps_per_sync * self.plant.dt)
        self.plant.step(current, self._steps_per_sync)
        if states.ramp_start_ns is not None and states.standing:
            states.ramp_finished()
        self._refresh_actuals()

    def _refresh_actuals(self) -> None:
        plant, motor, values = self.plant, self.motor, self._values
        values.update(zip(ACTUAL_KEYS, wire_actuals(
            plant.position_deg, plant.velocity_deg_s, plant.increments_per_rev,
            motor.count.offset, motor.demand(), self._switches.inputs(plant.position_deg),
            plant.applied_current_ma, values[RATED_KEY], self.states.statusword), strict=True))

    # ----------------------------------------------------------------------------- EMCY
    def _emcy(self, code: int, register: int, manufacturer: bytes = b"",
              raise_register: bool = True) -> None:
        values = self._values
        if raise_register and register:
            values[(ERROR_REGISTER, 0)] |= register | ERR_REG_GENERIC
        if self.nmt_state not in (NMT_PRE_OPERATIONAL, NMT_OPERATIONAL):
            return  # EMCY is not allowed in STOPPED
        payload = struct.pack("<HB", code, values[(ERROR_REGISTER, 0)]) + \
            manufacturer.ljust(5, b"\0")
        self._send([(EMCY_BASE + self.node_id, payload[:8])])

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
        if self.nmt_state == NMT_BOOT_UP:
            return
        if self._gone_after_ns and time.monotonic_ns() - self._heard_ns > self._gone_after_ns:
            self._master_gone()
            now = self._now()
        if self._fault_list:
            self._service_faults(now)
        if self.nmt_state == NMT_OPERATIONAL and self.pdos.on_event and \
                (events := self.pdos.event_frames(now)):
            self._send(events)  # event-driven TPDOs (transmission types 254, 255)
        period_ms = self._values[(PRODUCER_HEARTBEAT, 0)]
        if period_ms and (self._hb_next_ns is None or now >= self._hb_next_ns):
            if not self.faults.active("no_heartbeat"):
                self._send([(HEARTBEAT_BASE + self.node_id, bytes([self.nmt_state]))])
            late = self._hb_next_ns is None or now - self._hb_next_ns > period_ms * 1_000_000
            base = now if late else self._hb_next_ns
            self._hb_next_ns = base + period_ms * 1_000_000
        consumer_ms = self._values[(CONSUMER_HEARTBEAT, 1)] & 0xFFFF
        if self._hb_consumer_armed and now - self._hb_last_ns > consumer_ms * 1_000_000:
            self._hb_consumer_armed = False
            self._communication_lost(CAUSE_HEARTBEAT)
        sync_ms = self._values[(SYNC_LOSS_TIMEOUT, 0)]
        if self._sync_armed and sync_ms and now - self._sync_last_ns > sync_ms * 1_000_000:
            self._sync_armed = False
            self._communication_lost(CAUSE_SYNC)
        ramp_start = self.states.ramp_start_ns
        if ramp_start is not None and \
                now - ramp_start > self.config.quick_stop_timeout_ms * 1_000_000:
            self.states.ramp_finished()

    def _service_faults(self, now: int) -> None:
        """Delayed TPDOs that are due; an ``emcy`` fault raises its EMCY and FAULT once."""
        while self._delayed and self._delayed[0][0] <= now:
            self._send(self._delayed.pop(0)[1])
        for fault in self.faults.active("emcy"):
            if self.faults.hit(fault) == 1:
                self.states.fault(fault.params["code"], error_register_bit(fault.params["code"]))

    def _master_gone(self) -> None:
        """The lockstep master went silent for longer than it said it could be: its time
        stops here. Driving, the drive reacts as to a SYNC loss; then it keeps its own clock
        (``auto``; ``sync`` stays on SYNC time)."""
        self._gone_after_ns = 0
        if self.state in (OPERATION_ENABLED, QUICK_STOP_ACTIVE):
            self._sync_armed = False
            self._communication_lost(CAUSE_SYNC)
        if self.clock == "auto":
            self._values[(TIME_BASE, 0)] = 0
            self._own_clock_again()

    def _communication_lost(self, cause: int) -> None:
        if self.state in (OPERATION_ENABLED, QUICK_STOP_ACTIVE):
            self.states.fault(EMCY_HEARTBEAT, ERR_REG_COMMUNICATION, cause)
        else:  # no torque to take away: report it and flag a warning in the statusword
            self.states.comm_warning = True
            self._emcy(EMCY_HEARTBEAT, ERR_REG_COMMUNICATION, bytes([cause]))
            self._values[(STATUSWORD, 0)] = self.statusword
