"""The cyclic exchange over EtherCAT: the RxPDO (controlword and the mode's set point, packed
as the CAN RPDO is) staged as the slave's outputs, one LRW frame a cycle, the TxPDOs read from
its inputs, and the frame's working counter checked every cycle: a wrong or missing one is a
stale cycle (the last feedback again), which the watchdog counts to a lost link as on CAN; in
lockstep, no frame back at all within the bound is a gone drive.

The feedback is the CAN exchange's (:class:`~hil.drivers.canopen.cyclic.CyclicExchange`, whose
decoding, turn counting and watchdog this reuses): ``x(k+1)`` after the set point of cycle
``k``, hil's emulated slave running its cycle inside the frame as it passes.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from hil.contracts import LinkWatchdog
from hil.drivers.canopen.cyclic import CyclicExchange, Feedback, tpdo_decoder
from hil.drivers.canopen.errors import DriveGoneError, DriveLinkLostError
from hil.drivers.canopen.link import Link
from hil.drivers.canopen.nmt import HeartbeatProducer
from hil.drivers.ethercat.segment import NO_FRAME, Segment
from hil.protocols.cia402 import CW_DISABLE_VOLTAGE, PdoMap


class ProcessDataExchange(CyclicExchange):
    """Slave ``position``'s process data on ``segment``; ``before_cycle`` runs before each
    cycle is staged (queued SDO downloads), ``after_cycle`` after each answer (a look in the
    mailbox now and then)."""

    def __init__(self, segment: Segment, position: int, link: Link, node_id: int,
                 rpdo: PdoMap, tpdos: Sequence[PdoMap], *, rx_timeout_s: float, period_s: float,
                 watchdog: LinkWatchdog, silence_is_gone: bool, now_ns: Callable[[], int],
                 before_cycle: Callable[[], None] = lambda: None,
                 after_cycle: Callable[[Feedback], None] = lambda feedback: None) -> None:
        super().__init__(link, node_id, rpdo, tpdos, rx_timeout_s=rx_timeout_s,
                         period_s=period_s, watchdog=watchdog, silence_is_gone=silence_is_gone,
                         heartbeat=HeartbeatProducer(0, 0, now_ns), now_ns=now_ns,
                         other=lambda frame: None)
        self.segment, self.position = segment, position
        self.before_cycle, self.after_cycle = before_cycle, after_cycle
        self._inputs = []
        offset = 0
        for i, pdo in enumerate(tpdos):
            decoder = tpdo_decoder(pdo, i)
            self._inputs.append((offset, decoder.layout, decoder.slots))
            offset += decoder.layout.size
        self.input_size = offset
        self.controlword = CW_DISABLE_VOLTAGE  # the one the outputs hold: the last sent
        self.wkc_errors = 0   # cycles whose working counter was not the expected one
        self.no_frame = 0     # cycles whose frame did not come back in time

    def send(self, controlword: int, target: int, command_ma: float = 0.0) -> None:
        if self._awaiting:
            self.receive()
        self.before_cycle()
        self._command_ma = command_ma
        self._awaiting = True
        self._sent_ns = time.perf_counter_ns()
        self.cycle += 1
        self.controlword = controlword
        self.segment.stage(self.position, self._rpdo_frame(controlword, target))

    def receive(self, timeout_s: float | None = None) -> Feedback:
        if not self._awaiting:
            return super().receive()
        wait_ns = self._rx_timeout_ns if timeout_s is None else round(timeout_s * 1e9)
        try:
            wkc = self.segment.collect(wait_ns / 1e9)
        finally:
            self._awaiting = False
        expected = self.segment.expected_wkc
        inputs = self.segment.inputs(self.position)
        complete = wkc == expected and len(inputs) >= self.input_size
        if complete:
            rx = self._rx
            for offset, layout, slots in self._inputs:
                for slot, value in zip(slots, layout.unpack_from(inputs, offset), strict=True):
                    rx[slot] = value
        elif wkc == NO_FRAME:
            self.no_frame += 1
            if self._silence_is_gone:
                raise DriveGoneError(
                    f"no EtherCAT frame came back for {wait_ns / 1e9:g} s of wall "
                    f"time after cycle {self.cycle} (lockstep waits that long: "
                    "master.lockstep_timeout_ms): the drive is gone (stopped, unplugged, or "
                    "paused for longer)")
        else:
            self.wkc_errors += 1
        try:
            feedback = self._conclude(complete, True, wait_ns)
        except DriveLinkLostError as exc:
            raise DriveLinkLostError(f"{exc} (working counter {wkc}, expected {expected}: "
                                     f"{self.wkc_errors} wrong, {self.no_frame} frames lost)"
                                     ) from None
        self.after_cycle(feedback)
        return feedback

    def send_now(self, controlwords: list[int]) -> None:
        """Each controlword (target 0) in a frame of its own, at once, answers unread: the
        best effort of a master that lost its link."""
        for word in controlwords:
            self.controlword = word
            try:
                self.segment.slave(self.position).output = self._rpdo_frame(word, 0)
                self.segment.send()
            except Exception:  # a closed interface, a vanished slave: nothing more to do
                return

    def drain(self) -> None:
        """The answer of the last frame, if nobody read it."""
        self._awaiting = False
        self.segment.collect(0)

    def _take_waiting(self) -> None:
        """Nothing waits: a frame's answer is its own."""
