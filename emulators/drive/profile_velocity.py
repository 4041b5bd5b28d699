"""Profile velocity mode (PV): a velocity ramp towards the target velocity 0x60FF with the
profile acceleration 0x6083 (speeding up) and deceleration 0x6084 (slowing down), which the
drive's velocity loop follows; bit 8 halt ramps to a stop. Statusword bit 10 target reached:
the velocity within the velocity window 0x606D of the target (0 when halted) for 0x606E ms;
bit 12 speed zero: the velocity within the threshold 0x606F of zero."""

from __future__ import annotations

from hil.emulators.drive.motion import Axis, ModeMotion, Profile
from hil.protocols.cia402 import (
    CW_HALT,
    PROFILE_ACCELERATION,
    PROFILE_DECELERATION,
    SW_SPEED_ZERO,
    SW_TARGET_REACHED,
    TARGET_VELOCITY,
    VELOCITY_THRESHOLD,
    VELOCITY_WINDOW,
    VELOCITY_WINDOW_TIME,
)


class ProfileVelocity(ModeMotion):
    """PV's ramp and status (see the module)."""

    def __init__(self, axis: Axis) -> None:
        super().__init__(axis)
        self.forget()

    def forget(self) -> None:
        """The ramp starts from the axis' velocity."""
        count = self.axis.count
        self.profile = Profile(count.exact(), count.velocity())
        self.halted = False
        self.in_window_s: float | None = None

    def controlword(self, controlword: int, previous: int) -> None:
        self.halted = bool(controlword & CW_HALT)

    def _target(self) -> float:
        return 0.0 if self.halted else float(self.axis.value(TARGET_VELOCITY))

    def current(self, cycle_s: float) -> float:
        axis = self.axis
        self.profile.ramp_to(self._target(), axis.value(PROFILE_ACCELERATION),
                             axis.value(PROFILE_DECELERATION), cycle_s)
        if abs(axis.count.velocity() - self._target()) <= axis.value(VELOCITY_WINDOW):
            self.in_window_s = (self.in_window_s or 0.0) + cycle_s
        else:
            self.in_window_s = None
        return axis.loops.velocity(axis.count.degrees(self.profile.velocity))

    def status_bits(self) -> int:
        axis = self.axis
        reached = self.in_window_s is not None and \
            self.in_window_s * 1000.0 >= axis.value(VELOCITY_WINDOW_TIME)
        zero = abs(axis.count.velocity()) <= axis.value(VELOCITY_THRESHOLD)
        return (SW_TARGET_REACHED if reached else 0) | (SW_SPEED_ZERO if zero else 0)

    def demand(self) -> tuple[float, float]:
        return self.axis.count.exact(), self.profile.velocity
