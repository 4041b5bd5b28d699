"""The modes in which the drive moves the axis on its own: a profile position move (PP), a
profile velocity (PV) and a homing (HM), as the master drives them cycle by cycle.

The objects that shape the profiles are written at configure
(:func:`hil.drivers.canopen.profile.profile_writes`).

* :class:`PositionMove` (PP) and :class:`Homing` (HM) - what each cycle sends (the set point
  and the mode's controlword bits) from what the drive reported in the last: the
  new-set-point handshake (bit 4 up until statusword bit 12 acknowledges it, then down; done
  when bit 10 says the target is reached within the drive's position window), the homing
  (bit 4 up; done when bits 12 and 10 say attained and standing; bit 13 a homing error). A
  following error (bit 13 in PP) or a homing error is a :class:`MotionError` naming where the
  axis is. PV needs neither: its set point, a velocity, takes effect every cycle.
* :func:`run_motion` - a motion to its end on a master enabled in its mode, one cycle a
  period, within a time-out (its own line when it runs out).

The first feedback after a new set point or a homing start may still show the bits of the one
before (the drive reacts at the next SYNC): a move waits for the acknowledge, a homing for its
second feedback.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from hil.drivers.canopen.cyclic import Feedback
from hil.drivers.canopen.errors import DriveError
from hil.drivers.canopen.master import CanDriveMaster
from hil.protocols.cia402 import (
    CW_CHANGE_SET_IMMEDIATELY,
    CW_HOMING_START,
    CW_NEW_SET_POINT,
    HOME_OFFSET,
    SW_FOLLOWING_ERROR,
    SW_HOMING_ATTAINED,
    SW_HOMING_ERROR,
    SW_SET_POINT_ACK,
    SW_TARGET_REACHED,
)


class MotionError(DriveError):
    """A move or a homing the drive ended in error, or that ran out of time."""


class Motion(Protocol):
    """What a profile mode sends each cycle (:meth:`next`), until :attr:`done`."""

    what: str   # "PP move to 90 deg", "homing (method 37)": for errors and events
    done: bool

    def next(self, feedback: Feedback) -> tuple[float, int]:
        """The set point and controlword bits of the next cycle, from ``feedback``."""


class PositionMove:
    """A PP move to ``target_deg`` (multi-turn, in the master's frame): the new-set-point
    handshake, then the drive's profile until it reports the target reached."""

    def __init__(self, target_deg: float) -> None:
        self.target_deg = target_deg
        self.what = f"PP move to {target_deg:g} deg"
        self.done = False
        self.acknowledged = False
        self._armed = False  # bit 4 sent low once, so that it rises

    def next(self, feedback: Feedback) -> tuple[float, int]:
        status = feedback.statusword
        if status & SW_FOLLOWING_ERROR and self._armed:
            raise MotionError(f"{self.what}: following error (statusword 0x{status:04X}, bit "
                              f"13) at {feedback.position_deg:.3f} deg")
        if not self._armed:
            self._armed = True
            return self.target_deg, CW_CHANGE_SET_IMMEDIATELY
        if not self.acknowledged:
            self.acknowledged = bool(status & SW_SET_POINT_ACK)
            bits = 0 if self.acknowledged else CW_NEW_SET_POINT
            return self.target_deg, bits | CW_CHANGE_SET_IMMEDIATELY
        # the drive has seen bit 4 low once it drops its acknowledge: bit 10 is this target's
        self.done = bool(status & SW_TARGET_REACHED and not status & SW_SET_POINT_ACK)
        return self.target_deg, CW_CHANGE_SET_IMMEDIATELY


class Homing:
    """A homing by the method configured in the drive (0x6098, written at configure):
    ``method`` names it in errors; ``on_home`` is told once home is attained (the drive's
    position starts a frame of its own there: :func:`homing`)."""

    def __init__(self, method: int | None, on_home: Callable[[], None] = lambda: None) -> None:
        self.method = method
        self.what = "homing" + (f" (method {method})" if method is not None else "")
        self.done = False
        self.attained = False
        self._on_home = on_home
        self._armed = False  # bit 4 sent low once, so that it rises
        self._high = 0       # cycles sent with bit 4 up

    def next(self, feedback: Feedback) -> tuple[float, int]:
        status = feedback.statusword
        if self.attained:  # one more cycle: its feedback is in the new frame
            self.done = True
            return 0.0, 0
        if self._high >= 2:  # this feedback answers a cycle the start was seen in
            if status & SW_HOMING_ERROR:
                moving = "standing" if status & SW_TARGET_REACHED else "still moving"
                raise MotionError(f"{self.what}: the drive reports a homing error (statusword "
                                  f"0x{status:04X}, bit 13) at {feedback.position_deg:.3f} deg, "
                                  f"{moving}")
            if status & SW_HOMING_ATTAINED and status & SW_TARGET_REACHED:
                self.attained = True
                self._on_home()
                return 0.0, 0
        if not self._armed:
            self._armed = True
            return 0.0, 0
        self._high += 1
        return 0.0, CW_HOMING_START


def homing(master: CanDriveMaster, method: int) -> Homing:
    """A homing of ``master``'s drive by ``method``: once home, the master counts the turns of
    the drive's new frame from home, its position there the home offset (0x607C)."""
    offset = master.objects.read(HOME_OFFSET, 0, "<i")
    home_deg = 0.0 if offset is None else master.scaling.degrees(offset)
    master.cyclic.homing_starts()
    return Homing(method, lambda: master.cyclic.forget_turns(home_deg))


def run_motion(master: CanDriveMaster, motion: Motion, timeout_s: float,
               on_feedback: Callable[[Feedback], None] = lambda feedback: None) -> Feedback:
    """``motion`` on ``master`` (enabled in its mode) to its end, one cycle a period of the
    master's clock, each cycle's feedback to ``on_feedback``; the last feedback. A
    MotionError when the drive ends it in error, or when it has not ended after
    ``timeout_s``."""
    feedback = master.receive_feedback()
    for _ in master.periods(timeout_s):
        value, bits = motion.next(feedback)
        if motion.done:
            return feedback
        master.send_set_point(value, bits)
        feedback = master.receive_feedback()
        on_feedback(feedback)
    raise timed_out(motion, feedback, timeout_s)


def timed_out(motion: Motion, feedback: Feedback, timeout_s: float) -> MotionError:
    """``motion`` not done within ``timeout_s``: where the axis is, what the drive says."""
    return MotionError(f"{motion.what}: not done within {timeout_s:g} s (statusword "
                       f"0x{feedback.statusword:04X}, at {feedback.position_deg:.3f} deg)")
