"""The CiA 402 state machine's two words on EtherCAT (a
:class:`~hil.drivers.canopen.state.StateWords` channel): in the process data while the slave is
in OP, by SDO while it is not.

In OP the RxPDO carries the controlword every cycle, so a drive's own cycle overwrites an SDO
write of 0x6040 with it (or refuses the write), and many drives update 0x6041 only in the
TxPDO. So there each controlword goes out in the RxPDO of a cycle, with the mode's set point
holding the axis where it stands, and each statusword is a cycle's TxPDO; a read with no new
controlword repeats the last one the outputs held. The cycles are the cyclic exchange's (its
working counter, watchdog and lockstep rules), one period apart on the master's clock (in
lockstep each cycle is a period). Before OP (PRE-OP, or the segment scanned again after a lost
link) no process data flows and the words go by SDO, as on CAN."""

from __future__ import annotations

from collections.abc import Callable

from hil.drivers.canopen.cyclic import Feedback
from hil.drivers.canopen.state import MasterClock, StateWords
from hil.drivers.ethercat.cyclic import ProcessDataExchange
from hil.drivers.ethercat.segment import Segment


class ProcessDataWords:
    """The two words in ``cyclic``'s process data, a cycle each; ``hold()``: the set point
    that holds the axis (sent beside each controlword)."""

    def __init__(self, cyclic: ProcessDataExchange, hold: Callable[[], int],
                 clock: MasterClock, period_s: float) -> None:
        self.cyclic, self.hold, self.clock = cyclic, hold, clock
        self.period_ns = round(period_s * 1e9)
        self._next_ns: int | None = None  # when the next cycle is due on the master's clock

    def controlword(self, word: int) -> None:
        self._cycle(word)

    def statusword(self, timeout_s: float | None = None) -> int:
        return self._cycle(self.cyclic.controlword, timeout_s).statusword

    def pause(self) -> None:
        """Nothing to wait for: each read is a cycle of its own, a period after the last."""

    def _cycle(self, word: int, timeout_s: float | None = None) -> Feedback:
        clock = self.clock
        now_ns = clock.time_ns()
        if self._next_ns is not None and 0 < self._next_ns - now_ns <= self.period_ns:
            clock.sleep((self._next_ns - now_ns) / 1e9)
            now_ns = self._next_ns
        self._next_ns = now_ns + self.period_ns
        self.cyclic.send(word, self.hold())
        return self.cyclic.receive(timeout_s)


class SegmentWords:
    """Slave ``position``'s words: ``process_data`` while ``segment`` has it in OP, ``sdo``
    otherwise."""

    def __init__(self, segment: Segment, position: int, process_data: StateWords,
                 sdo: StateWords) -> None:
        self.segment, self.position = segment, position
        self.process_data, self.sdo = process_data, sdo

    @property
    def now(self) -> StateWords:
        """The channel the words take now."""
        return self.process_data if self.position in self.segment.in_op else self.sdo

    def controlword(self, word: int) -> None:
        self.now.controlword(word)

    def statusword(self, timeout_s: float | None = None) -> int:
        return self.now.statusword(timeout_s)

    def pause(self) -> None:
        self.now.pause()
