"""The safe stop of one drive or several in the same cycles: quick stop until every drive
stands (or the quick-stop time-out), then disable voltage in one cycle. One algorithm, on the
master's public stop cycles (:class:`StopCycles`): a master runs it for its drive alone
(:meth:`~hil.drivers.canopen.master.CanDriveMaster.safe_state`), an axis group for all its
drives (:meth:`~hil.drivers.canopen.axes.AxisGroup.stop_together`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol

from hil.drivers.canopen.cyclic import Feedback
from hil.drivers.canopen.errors import DriveError
from hil.drivers.canopen.sdo import SdoChannel
from hil.protocols.cia301 import SdoAbortError
from hil.protocols.cia402 import (
    CONTROLWORD,
    CW_DISABLE_VOLTAGE,
    CW_QUICK_STOP,
    OPERATION_ENABLED,
    QUICK_STOP_ACTIVE,
    STATUSWORD,
    state_of,
)


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


#: what a failed safe stop's line ends with
MAY_STILL_MOVE = "the axis may still move"


def last_report(feedback: Feedback | None) -> tuple[str, dict[str, Any]]:
    """What the drive last reported, as a clause (``it last reported OPERATION ENABLED
    (statusword 0x1237) at 79.600 deg, 0.0 deg/s, -300 mA``) and as data."""
    if feedback is None:
        return "it reported nothing", {}
    data = {"state": feedback.state, "statusword": feedback.statusword,
            "position_deg": feedback.position_deg, "velocity_deg_s": feedback.velocity_deg_s,
            "current_mA": feedback.current_ma, "cycle": feedback.cycle, "fresh": feedback.fresh}
    stale = "" if feedback.fresh else ", its last answer repeated: none came in that cycle"
    return (f"it last reported {feedback.state} (statusword 0x{feedback.statusword:04X}) at "
            f"{feedback.position_deg:.3f} deg, {feedback.velocity_deg_s:.1f} deg/s, "
            f"{feedback.current_ma:.0f} mA (cycle {feedback.cycle}{stale})"), data


def confirm_stopped(sdo: SdoChannel, feedback: Feedback | None, event: Callable[..., None],
                    reached: bool) -> None:
    """After a link lost while driving (``reached``: the bus could be reconnected): the
    drive's state read again by SDO, and disable voltage sent by SDO if it is still enabled.
    ``drive.safe_stop`` when it is disabled or in a fault (its own reaction);
    ``drive.safe_stop_failed`` when that cannot be confirmed. ``event`` is the master's."""
    n, timeout = sdo.node_id, sdo.timeout_s
    said, last = last_report(feedback)
    driving = (OPERATION_ENABLED, QUICK_STOP_ACTIVE)
    try:
        if not reached:
            raise DriveError("the bus cannot be reached again")
        state = state_of(sdo.read_int(STATUSWORD, 0, "<H", timeout))
        if state in driving:
            sdo.write(CONTROLWORD, 0, CW_DISABLE_VOLTAGE, "<H", timeout_s=timeout)
            state = state_of(sdo.read_int(STATUSWORD, 0, "<H", timeout))
    except (DriveError, SdoAbortError) as exc:
        event("drive.safe_stop_failed", f"drive node {n}: the link was lost while driving and "
              f"its state cannot be confirmed since ({exc}); {said}: {MAY_STILL_MOVE} unless "
              "its own watchdog stopped it", level="error", last=last)
        return
    if state in driving:
        event("drive.safe_stop_failed", f"drive node {n} is still {state} after the lost link "
              f"and disable voltage by SDO: {MAY_STILL_MOVE}", level="error", state=state,
              last=last)
    else:
        event("drive.safe_stop", f"drive node {n} stopped: {state}, confirmed by SDO after the "
              "lost link", state=state)
