"""The safe stop of one drive or several in the same cycles: quick stop until every drive
stands (or the quick-stop time-out), then disable voltage in one cycle. One algorithm, on the
master's public stop cycles (:class:`StopCycles`): a master runs it for its drive alone
(:meth:`~hil.drivers.canopen.master.CanDriveMaster.safe_state`), an axis group for all its
drives (:meth:`~hil.drivers.canopen.axes.AxisGroup.stop_together`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Protocol

from hil.drivers.canopen.cyclic import Feedback
from hil.drivers.canopen.errors import DriveError
from hil.protocols.cia402 import CW_DISABLE_VOLTAGE, CW_QUICK_STOP


class StopCycles(Protocol):
    """One drive's part of a safe stop (the master's stop cycles)."""

    def begin_stop(self) -> bool: ...

    def quick_stop_cycles(self) -> Iterator[None]: ...

    def send_stop_cycle(self, controlword: int) -> None: ...

    def receive_stop_cycle(self) -> Feedback: ...

    def report_stop_cycle(self, feedback: Feedback) -> None: ...

    def stands(self, feedback: Feedback) -> bool: ...

    def end_stop(self, outcome: Feedback | DriveError) -> None: ...


def stop_together(drives: Sequence[StopCycles],
                  end_cycle: Callable[[], None] = lambda: None) -> None:
    """Quick stop on every enabled drive of ``drives`` in the same cycles, until all stand (or
    the quick-stop time-out), then disable voltage, in one cycle too: each cycle every drive's
    frames, then ``end_cycle()`` (an axis bus's SYNC; a lone master sends its own), then every
    drive's feedback, handed to its ``on_stop_cycle``. Silent: failures become
    ``drive.safe_stop_failed`` events."""
    stopping = [drive for drive in drives if drive.begin_stop()]
    if not stopping:
        return

    def cycle(controlword: int) -> list[Feedback]:
        for drive in stopping:
            drive.send_stop_cycle(controlword)
        end_cycle()
        feedbacks = [drive.receive_stop_cycle() for drive in stopping]
        for drive, feedback in zip(stopping, feedbacks, strict=True):
            drive.report_stop_cycle(feedback)
        return feedbacks

    outcomes: Sequence[Feedback | DriveError]
    try:
        for _ in stopping[0].quick_stop_cycles():
            feedbacks = cycle(CW_QUICK_STOP)
            if all(drive.stands(feedback)
                   for drive, feedback in zip(stopping, feedbacks, strict=True)):
                break
        outcomes = cycle(CW_DISABLE_VOLTAGE)
    except DriveError as exc:
        outcomes = [exc] * len(stopping)
    for drive, outcome in zip(stopping, outcomes, strict=True):
        drive.end_stop(outcome)
