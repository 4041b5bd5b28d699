"""The cyclic exchange (the hot path): RPDO + SYNC (+ the master's heartbeat, + a queued SDO
download) in one transmission, then the TPDOs that answer that SYNC.

The TPDOs are the master's layout (:data:`hil.protocols.cia402.TPDO_LAYOUTS`): TPDO1 (statusword,
position) and TPDO2 (velocity, torque), or TPDO1 alone (statusword, position, torque), each
decoded by the objects it maps. Without a velocity on the wire, the velocity is the position's
change since the last fresh feedback over the cycles between (a backward difference); without
a torque (a drive that has no 0x6077, whose maps leave it out) the current is NaN.

Every feedback is bound to its SYNC:

* before each SYNC, every frame already waiting is taken: TPDOs there answer an older SYNC
  whose wait is over - they are late (``late_frames``) and discarded;
* after the SYNC, the first of each TPDO that arrive before the deadline (``rx_timeout`` after
  the SYNC) make the feedback; one TPDO of this cycle is never combined with one of another,
  and TPDOs that miss the deadline are never used for a later cycle: the feedback is then
  stale (the last values again, ``fresh`` False);
* where the drive echoes the SYNC counter (``sync_echo``: an object holding the counter of the
  SYNC it answers, mapped as the last byte of every TPDO; the SYNC counter on through 0x1019),
  a TPDO whose echo is not this SYNC's counter is late wherever it arrives. Without an echo,
  late TPDOs that arrive after the next SYNC but before that SYNC's own answer cannot be told
  from it: they can stand in for that one cycle, and are then found out (late) at the next
  SYNC.
"""

from __future__ import annotations

import math
import os
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

from hil.contracts import LinkWatchdog, PollBudget
from hil.drivers.canopen.errors import DriveError, DriveGoneError, DriveLinkLostError
from hil.drivers.canopen.link import Link
from hil.drivers.canopen.nmt import HeartbeatProducer
from hil.drivers.canopen.scaling import DriveScaling
from hil.protocols.can_frames import Frame
from hil.protocols.cia301 import SYNC_COB_ID
from hil.protocols.cia402 import (
    POSITION_ACTUAL,
    STATUSWORD,
    SW_HOMING_ATTAINED,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
    PdoMap,
    state_of,
)

POLL_WAIT_MAX_NS = 2_000_000  # TPDO waits up to this long poll the bus instead of blocking
LONG_WAIT_POLL_NS = 500_000  # a longer one (lockstep over a bus) polls at most this long
SYNC_COUNTER_MAX = 240  # 0x1019 written when the echo is on: the SYNC counter runs 1..240
SYNC_FRAME: Frame = (SYNC_COB_ID, b"")  # without the echo: a SYNC without a counter
# the feedback objects a TPDO carries: their slot in the raw feedback and their wire format
FEEDBACK_OBJECTS = {STATUSWORD: (0, "H"), POSITION_ACTUAL: (1, "i"), VELOCITY_ACTUAL: (2, "i"),
                    TORQUE_ACTUAL: (3, "h")}
FEEDBACK_NAMES = ("statusword", "position", "velocity", "torque")  # by slot
VELOCITY_SLOT = 2  # one a master can do without: derived from the position
TORQUE_SLOT = 3    # and one a drive may lack (no 0x6077): no current measured


class TpdoDecoder(NamedTuple):
    """How one TPDO's data becomes feedback: its bit among the cycle's TPDOs, the layout of its
    feedback objects (first in the PDO; a SYNC counter echo, if any, follows them), the slot
    of each in the raw feedback and, where those slots follow each other, their slice (the
    values stored in one assignment)."""

    bit: int
    layout: struct.Struct
    slots: tuple[int, ...]
    span: slice | None


def tpdo_decoder(pdo: PdoMap, index: int) -> TpdoDecoder:
    """The decoder of ``pdo``, the ``index``-th TPDO of the layout: its feedback objects
    first, then at most one byte (the SYNC counter echo)."""
    feedback = [entry for entry in pdo.entries if entry[0] in FEEDBACK_OBJECTS]
    if list(pdo.entries[:len(feedback)]) != feedback or \
            [bits for _, _, bits in pdo.entries[len(feedback):]] not in ([], [8]):
        raise ValueError(f"TPDO 0x{pdo.comm:04X}: feedback objects first, then at most the "
                         "SYNC counter echo byte")
    slots = tuple(FEEDBACK_OBJECTS[i][0] for i, _, _ in feedback)
    span = slice(slots[0], slots[-1] + 1) \
        if slots and slots == tuple(range(slots[0], slots[-1] + 1)) else None
    return TpdoDecoder(1 << index,
                       struct.Struct("<" + "".join(FEEDBACK_OBJECTS[i][1] for i, _, _ in feedback)),
                       slots, span)


class Feedback(NamedTuple):
    """What the drive reported for one cycle (``fresh`` False: the TPDOs did not arrive in
    time and the values are the previous cycle's). A named tuple: built every cycle, and a
    frozen dataclass costs several times as much to build."""

    position_deg: float       # multi-turn, unwrapped by the master
    velocity_deg_s: float
    current_ma: float         # torque actual, as motor current (NaN: the drive has none)
    statusword: int
    position_increments: int  # as on the wire: modulo one revolution
    cycle: int                # SYNC count of this master
    t_ns: int                 # master time on reception
    fresh: bool
    rtt_us: float             # SYNC sent -> both TPDOs received (wall clock)
    command_ma: float         # the current the cycle commanded (after the clamp)

    @property
    def state(self) -> str:
        return state_of(self.statusword)


#: a :class:`Feedback` from its fields in order, in one call (``Feedback(...)`` makes two)
new_feedback = tuple.__new__


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


class CyclicExchange:
    """One node's cyclic PDO traffic over ``link``. Frames that are not its TPDOs go to
    ``other`` (SDO answers, EMCY, heartbeats) as they come."""

    def __init__(self, link: Link, node_id: int, rpdo: PdoMap, tpdos: Sequence[PdoMap], *,
                 rx_timeout_s: float, period_s: float, watchdog: LinkWatchdog,
                 silence_is_gone: bool = False,
                 heartbeat: HeartbeatProducer, now_ns: Callable[[], int],
                 other: Callable[[Frame], None]) -> None:
        self.link = link
        self.node_id = node_id
        self.stats = LinkStats()
        self.watchdog = watchdog
        self.heartbeat = heartbeat
        self._now_ns = now_ns
        self._other = other
        self._rx_timeout_ns = round(rx_timeout_s * 1e9)
        # lockstep over a bus: a wait with no frame at all is not a late drive but a gone one
        self._silence_is_gone = silence_is_gone
        self._heard = False  # a frame came since the last SYNC
        self._poll = PollBudget(LONG_WAIT_POLL_NS)  # how a long wait polls before it blocks
        self.use_rpdo(rpdo)
        self.use_tpdos(tpdos)
        self._period_s = period_s
        self._last_fresh: tuple[float, int] | None = None  # position, cycle (derived velocity)
        self._homing: bool | None = None  # a homing runs: None, then whether bit 12 was low
        self.scaling = DriveScaling()
        self.echo = False          # TPDOs carry the SYNC counter as their last byte
        self.sync_counter = 0      # the counter of the last SYNC sent (echo on)
        self.feedback: Feedback | None = None
        self.extra_frames: Callable[[], list[Frame]] = list  # a queued SDO download, if any
        self.cycle = 0
        self._awaiting = False
        self._got = 0
        self._rx: list[int] = [0, 0, 0, 0]  # statusword, position, velocity, torque
        self._sent_ns = 0
        self._command_ma = 0.0
        self._turns = 0
        self._last_raw: int | None = None
        self._near: int | None = None  # after forget_turns: the first position's turn

    # -- set-up ---------------------------------------------------------------------------
    def use_rpdo(self, rpdo: PdoMap) -> None:
        """Send ``rpdo`` from the next cycle on: the controlword (UNSIGNED16), then the mode's
        set point if it has one (INTEGER16 torque, INTEGER32 position or velocity)."""
        self._rpdo_id = rpdo.cob_id(self.node_id)
        sizes = [bits for _, _, bits in rpdo.entries[1:]]
        pack = struct.Struct("<H" + "".join("h" if b == 16 else "i" for b in sizes)).pack
        # the RPDO's data of a controlword and a target (one the mode has none of: left out)
        self._rpdo_frame: Callable[[int, int], bytes] = pack if sizes else \
            (lambda controlword, _target: pack(controlword))

    def use_tpdos(self, tpdos: Sequence[PdoMap]) -> None:
        """Decode ``tpdos`` from the next cycle on: they carry the statusword and the position;
        without the velocity it is derived from the position, without the torque (a drive
        that has no 0x6077) the current is not measured (NaN)."""
        self._decoders = {pdo.cob_id(self.node_id): tpdo_decoder(pdo, i)
                          for i, pdo in enumerate(tpdos)}
        self._all = (1 << len(tpdos)) - 1  # every TPDO of the cycle received
        slots = {slot for decoder in self._decoders.values() for slot in decoder.slots}
        missing = [name for slot, name in enumerate(FEEDBACK_NAMES)
                   if slot not in slots and slot not in (VELOCITY_SLOT, TORQUE_SLOT)]
        if missing:
            raise ValueError(f"the TPDOs carry no {' and no '.join(missing)}: a feedback needs "
                             "the statusword and the position")
        self._derive_velocity = VELOCITY_SLOT not in slots
        self.measures_current = TORQUE_SLOT in slots

    @property
    def turns(self) -> int:
        """The turns counted on the drive's position so far (where it wraps: one turn)."""
        return self._turns

    def forget_turns(self, near_deg: float = 0.0) -> None:
        """The drive's position starts a frame of its own (a homing set it): the turns counted
        anew, the next position taken on the turn nearest ``near_deg`` (where the frame puts
        the axis: home; a drive that counts one turn says -5 deg as 355)."""
        self._turns, self._last_raw, self._last_fresh = 0, None, None
        self._near = self.scaling.counts(near_deg)

    def homing_starts(self) -> None:
        """A homing runs: the feedback whose statusword says homing attained (bit 12 rising)
        may hold the position in the drive's new frame already, so no velocity is derived
        from it and the one before (the axis stands there: bit 10)."""
        self._homing = False

    def start(self, feedback_raw: tuple[int, int, int, int] | None) -> Feedback:
        """Enabled: the first feedback from values read by SDO (statusword, position,
        velocity, torque), or (None) the last cycle's answer (a drive enabled through the
        process data); the master's heartbeat and the watchdog start afresh."""
        if feedback_raw is not None:
            self._rx = list(feedback_raw)
        self._last_fresh = None  # the velocity read by SDO is this feedback's
        self._awaiting = False
        self.heartbeat.restart()
        self.watchdog.success()
        self.feedback = self._make_feedback(fresh=True, rtt_us=0.0)
        return self.feedback

    @property
    def awaiting(self) -> bool:
        """A cycle was sent whose answer has not been read."""
        return self._awaiting

    # -- one cycle ---------------------------------------------------------------------------
    def send(self, controlword: int, target: int, command_ma: float = 0.0) -> None:
        """The last cycle's answer, if nobody read it (its deadline kept); what else waits
        (older answers: late); then RPDO + SYNC in one transmission."""
        if self._awaiting:
            self.receive()
        self._take_waiting()
        # a queued SDO download first: the drive takes it before it latches this cycle
        frames: list[Frame] = self.extra_frames()
        frames.append((self._rpdo_id, self._rpdo_frame(controlword, target)))
        if self.echo:
            self.sync_counter = self.sync_counter % SYNC_COUNTER_MAX + 1
            frames.append((SYNC_COB_ID, bytes([self.sync_counter])))
        else:
            frames.append(SYNC_FRAME)
        if self.heartbeat.due():
            frames.append(self.heartbeat.frame)
        self._command_ma = command_ma
        self._got = 0
        self._heard = False
        self._awaiting = True
        self._sent_ns = time.perf_counter_ns()
        self.link.send(frames)
        self.cycle += 1

    def receive(self, timeout_s: float | None = None) -> Feedback:
        """The TPDO pair of the last SYNC, waiting at most until ``rx_timeout`` (or
        ``timeout_s``) after it; without a cycle sent since the last call, the last feedback
        again."""
        if not self._awaiting:
            if self.feedback is None:
                raise DriveError("no feedback yet: enable the drive first")
            return self.feedback
        wait_ns = self._rx_timeout_ns if timeout_s is None else round(timeout_s * 1e9)
        recv, dispatch = self.link.recv, self._dispatch
        every = self._all
        try:
            # an answer already here (in lockstep; in real time one that travelled while the
            # loop slept) is read without a clock or a poll budget: every axis pays this a tick
            while self._got != every and (frame := recv(0.0)) is not None:
                dispatch(frame)
            if self._got != every:
                self._wait_for_rest(wait_ns)
        finally:
            self._awaiting = False
        return self._conclude(self._got == every, self._heard, wait_ns)

    def _wait_for_rest(self, wait_ns: int) -> None:
        """The rest of the answer, waited for until ``wait_ns`` after the SYNC."""
        # measured from the SYNC: in the split form the TPDOs have travelled while the loop
        # slept, and a late pair costs the tick only what is left of the wait
        deadline_ns = self._sent_ns + wait_ns
        recv, dispatch = self.link.recv, self._dispatch
        clock = time.perf_counter_ns
        # a wait of a cycle or so is spent polling: a thread blocked in select() is woken up
        # 50 us to several hundred us after the frame arrives (more on a virtual machine); a
        # longer one (lockstep over a bus) polls for as long as a drive takes to answer while
        # that pays (PollBudget), then blocks, leaving the CPU to the drive's process. Past the
        # deadline, what is already here is still read: a master held up (a busy machine) must
        # not call an answer that came in time late.
        long_wait = wait_ns > POLL_WAIT_MAX_NS
        if long_wait:
            self._poll.start(clock())
        every = self._all
        while self._got != every:
            now = clock()
            over = now >= deadline_ns
            look = over or not long_wait or self._poll.polling(now)
            frame = recv(0.0 if look else (deadline_ns - now) / 1e9)
            if frame is not None:
                dispatch(frame)
            elif over:
                break
            elif long_wait and look:  # the drive's process may be waiting for this core
                os.sched_yield()

    def _conclude(self, complete: bool, heard: bool, wait_ns: int) -> Feedback:
        """The cycle's feedback: fresh when its answer is ``complete``, else the last one
        again (stale), which the watchdog counts; in lockstep, nothing ``heard`` within
        ``wait_ns`` is a gone drive."""
        stats = self.stats
        stats.cycles += 1
        if complete:
            stats.fresh += 1
            self.watchdog.success()
            rtt_us = (time.perf_counter_ns() - self._sent_ns) / 1e3
            self.feedback = self._make_feedback(fresh=True, rtt_us=rtt_us)
            return self.feedback
        if self._silence_is_gone and not heard:
            raise DriveGoneError(
                f"nothing on the bus for {wait_ns / 1e9:g} s of wall time after "
                f"SYNC {self.cycle} (lockstep waits that long: master.lockstep_timeout_ms): "
                "the drive is gone (stopped, disconnected, or paused for longer)")
        stats.stale += 1
        lost = self.watchdog.failure()
        stats.longest_stale_run = self.watchdog.longest_run
        previous = self.feedback
        if previous is None:
            self.feedback = self._make_feedback(fresh=False, rtt_us=0.0)
        else:
            self.feedback = Feedback(
                previous.position_deg, previous.velocity_deg_s, previous.current_ma,
                previous.statusword, previous.position_increments, self.cycle,
                self._now_ns(), False, 0.0, self._command_ma)
        if lost:
            raise DriveLinkLostError(f"no TPDO for {self.watchdog.run} cycles")
        return self.feedback

    def send_now(self, controlwords: list[int]) -> None:
        """RPDO (each controlword, target 0) + SYNC, at once, no bookkeeping, as far as the
        link lets it: the best effort of a master that lost its link."""
        for word in controlwords:
            try:
                self.link.send([(self._rpdo_id, self._rpdo_frame(word, 0)), SYNC_FRAME])
            except DriveError:
                return

    def drain(self) -> None:
        """Every frame already here, read now (TPDOs among them are late): before a recovery,
        or before the drive's heartbeat is judged silent."""
        self._awaiting = False
        self._take_waiting()

    def _take_waiting(self) -> None:
        """Every frame already here, before the next SYNC: TPDOs among them are late."""
        recv, dispatch = self.link.recv, self._dispatch
        while (frame := recv(0)) is not None:
            dispatch(frame)

    def _dispatch(self, frame: Frame) -> None:
        self._heard = True
        decoder = self._decoders.get(frame[0])
        if decoder is None:
            self._other(frame)
            return
        data = frame[1]
        bit, layout, slots, span = decoder
        size, echo = layout.size, self.echo
        if len(data) < size + echo:
            self.stats.malformed_frames += 1
        elif not self._awaiting or self._got & bit or (echo and data[size] != self.sync_counter):
            self.stats.late_frames += 1
        elif span is not None:
            self._rx[span] = layout.unpack_from(data)
            self._got |= bit
        else:
            rx = self._rx
            for slot, value in zip(slots, layout.unpack_from(data), strict=True):
                rx[slot] = value
            self._got |= bit

    def _make_feedback(self, fresh: bool, rtt_us: float) -> Feedback:
        statusword, raw, velocity, torque = self._rx
        scaling = self.scaling
        turn = scaling.counts_per_turn
        last_raw = self._last_raw
        if last_raw is not None:
            step = raw - last_raw
            if step > turn // 2:
                self._turns -= 1
            elif step < -(turn // 2):
                self._turns += 1
        elif self._near is not None:
            self._turns, self._near = round((self._near - raw) / turn), None
        self._last_raw = raw
        per_count = scaling.degrees_per_count  # DriveScaling.degrees, without two calls
        position_deg = (self._turns * turn + raw) * per_count
        velocity_deg_s = velocity * per_count
        if self._derive_velocity and fresh:
            if self._homing is not None:
                if not statusword & SW_HOMING_ATTAINED:
                    self._homing = True
                elif self._homing:
                    self._homing, self._last_fresh = None, None
            before = self._last_fresh
            if before is not None and self.cycle > before[1]:
                velocity_deg_s = (position_deg - before[0]) / (
                    (self.cycle - before[1]) * self._period_s)
            self._last_fresh = (position_deg, self.cycle)
        # DriveScaling.milliamps, without a call
        current_ma = torque * scaling.rated_current_ma / 1000.0 if self.measures_current \
            else math.nan
        return new_feedback(Feedback, (position_deg, velocity_deg_s, current_ma, statusword, raw,
                                       self.cycle, self._now_ns(), fresh, rtt_us,
                                       self._command_ma))
