"""Profile position mode (PP): a trapezoidal profile (0x6081 profile velocity, 0x6083
acceleration, 0x6084 deceleration) towards the target position 0x607A, which the drive takes
on the new-set-point handshake.

* Controlword bit 4 rising: take 0x607A (bit 6: relative to the target before it) and
  acknowledge it (statusword bit 12, until bit 4 falls). While a move is under way the new
  target waits for its end (bit 12 stays set: the one-place buffer is full), unless bit 5
  (change set immediately) makes it replace the move at once.
* Bit 8 halt: slow down with 0x6084 and stand; the move goes on when the bit falls.
* Statusword bit 10 target reached: the profile has ended and the axis stayed within the
  position window 0x6067 of the target for 0x6068 ms (halted: standing); bit 13 following
  error: the axis beyond 0x6065 of the profile's demand (0xFFFFFFFF: off).

Positions are absolute in the drive's multi-turn count (the one 0x6064 carries modulo one
turn; homing sets it): a target is not folded into one turn."""

from __future__ import annotations

from hil.emulators.drive.motion import Axis, ModeMotion, Profile
from hil.protocols.cia402 import (
    CW_CHANGE_SET_IMMEDIATELY,
    CW_HALT,
    CW_NEW_SET_POINT,
    CW_RELATIVE,
    FOLLOWING_ERROR_WINDOW,
    POSITION_WINDOW,
    POSITION_WINDOW_TIME,
    PROFILE_ACCELERATION,
    PROFILE_DECELERATION,
    PROFILE_VELOCITY,
    SW_FOLLOWING_ERROR,
    SW_SET_POINT_ACK,
    SW_TARGET_REACHED,
    TARGET_POSITION,
)

WINDOW_OFF = 0xFFFF_FFFF  # CiA 402: a window of all ones is no window


class ProfilePosition(ModeMotion):
    """PP's profile generator and handshake (see the module)."""

    def __init__(self, axis: Axis) -> None:
        super().__init__(axis)
        self.profile = Profile()
        self.forget()

    def forget(self) -> None:
        """Standing where the axis is, that position the target, nothing buffered."""
        count = self.axis.count
        self.profile = Profile(count.exact(), 0.0)
        self.target = float(count.counts())
        self.buffered: float | None = None
        self.acknowledged = False
        self.halted = False
        self.at_target = True      # the profile stands at the target
        self.in_window_s: float | None = None  # how long the axis has been within the window
        self.following_error = False

    def controlword(self, controlword: int, previous: int) -> None:
        self.halted = bool(controlword & CW_HALT)
        if not controlword & CW_NEW_SET_POINT:
            self.acknowledged = self.buffered is not None
            return
        if previous & CW_NEW_SET_POINT:
            return  # no rising edge: nothing new
        base = self.buffered if self.buffered is not None else self.target
        given = self.axis.value(TARGET_POSITION)
        target = base + given if controlword & CW_RELATIVE else float(given)
        if self.at_target or controlword & CW_CHANGE_SET_IMMEDIATELY:
            self._take(target)
        else:
            self.buffered = target
        self.acknowledged = True

    def _take(self, target: float) -> None:
        self.target, self.at_target, self.in_window_s = target, False, None

    def current(self, cycle_s: float) -> float:
        axis, profile = self.axis, self.profile
        if self.halted:
            profile.stop(axis.value(PROFILE_DECELERATION), cycle_s)
        elif not self.at_target:
            self.at_target = profile.move_to(
                self.target, axis.value(PROFILE_VELOCITY), axis.value(PROFILE_ACCELERATION),
                axis.value(PROFILE_DECELERATION), cycle_s)
            if self.at_target and self.buffered is not None:
                self._take(self.buffered)
                self.buffered = None
                self.acknowledged = bool(axis.states.controlword & CW_NEW_SET_POINT)
        actual = axis.count.exact()
        window = axis.value(FOLLOWING_ERROR_WINDOW)
        self.following_error = window != WINDOW_OFF and abs(profile.position - actual) > window
        if self.at_target and abs(self.target - actual) <= axis.value(POSITION_WINDOW):
            self.in_window_s = (self.in_window_s or 0.0) + cycle_s
        else:
            self.in_window_s = None
        return axis.loops.position(axis.count.degrees(profile.position - actual),
                                   axis.count.degrees(profile.velocity))

    def status_bits(self) -> int:
        if self.halted:
            reached = self.axis.standing
        else:
            reached = self.at_target and self.in_window_s is not None and \
                self.in_window_s * 1000.0 >= self.axis.value(POSITION_WINDOW_TIME)
        return ((SW_TARGET_REACHED if reached else 0)
                | (SW_SET_POINT_ACK if self.acknowledged else 0)
                | (SW_FOLLOWING_ERROR if self.following_error else 0))

    def demand(self) -> tuple[float, float]:
        return self.profile.position, self.profile.velocity
