"""The cyclic synchronous modes' motion: the drive follows a set point the master sends every
SYNC. CST applies the target torque 0x6071 (above the trip level: the over-current fault),
CSP closes its own position loop on 0x607A (P with velocity feed-forward, the target's change
per cycle, around a velocity P loop; on the wire the target is modulo one turn: the short way
round), CSV its velocity loop on 0x60FF."""

from __future__ import annotations

from hil.emulators.drive.motion import Axis, ModeMotion
from hil.protocols.cia301 import EMCY_OVERCURRENT, ERR_REG_CURRENT
from hil.protocols.cia402 import RATED_CURRENT, TARGET_POSITION, TARGET_TORQUE, TARGET_VELOCITY

OVERCURRENT_TRIP = 0x2002  # the emulator's trip level [mA] (manufacturer object)
TORQUE_KEY, RATED_KEY, TRIP_KEY = (TARGET_TORQUE, 0), (RATED_CURRENT, 0), (OVERCURRENT_TRIP, 0)


def wrap_degrees(delta_deg: float) -> float:
    """``delta_deg`` folded into [-180, 180)."""
    return (delta_deg + 180.0) % 360.0 - 180.0


class CyclicTorque(ModeMotion):
    """CST: the target torque, per mille of the rated current."""

    def current(self, cycle_s: float) -> float:
        values = self.axis.values
        wanted: float = values[TORQUE_KEY] * values[RATED_KEY] / 1000.0
        if abs(wanted) > values[TRIP_KEY]:
            self.axis.states.fault(EMCY_OVERCURRENT, ERR_REG_CURRENT)
        return wanted


class CyclicPosition(ModeMotion):
    """CSP: the drive's position loop on the target, modulo one turn."""

    def __init__(self, axis: Axis) -> None:
        super().__init__(axis)
        self.last_target_deg: float | None = None

    def forget(self) -> None:
        """The feed-forward starts afresh, from the target held now (an enabled drive holds
        0x607A from then on, whether a cycle has run since or not)."""
        self.last_target_deg = self._target_deg()

    def _target_deg(self) -> float:
        return self.axis.values[(TARGET_POSITION, 0)] * 360.0 / self.axis.plant.increments_per_rev

    def current(self, cycle_s: float) -> float:
        plant = self.axis.plant
        target_deg = self._target_deg()
        previous, self.last_target_deg = self.last_target_deg, target_deg
        feed_forward = 0.0 if previous is None else wrap_degrees(target_deg - previous) / cycle_s
        error = wrap_degrees(target_deg - plant.position_deg - self.axis.count.offset_deg)
        return self.axis.loops.position(error, feed_forward)


class CyclicVelocity(ModeMotion):
    """CSV: the drive's velocity loop on the target velocity [increments/s]."""

    def current(self, cycle_s: float) -> float:
        axis = self.axis
        return axis.loops.velocity(axis.count.degrees(axis.value(TARGET_VELOCITY)))
