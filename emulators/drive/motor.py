"""The emulated drive's current loops: the current it applies each cycle, in its mode and
state - CST the target torque (above the trip level: the over-current fault), CSP its own
position loop (P with velocity feed-forward, around a velocity P loop), a ramp (quick stop,
fault reaction) its velocity loop braking at the current limit - and whether it had to limit
it (statusword bit 11)."""

from __future__ import annotations

import math
from typing import Any

from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.objects import Key
from hil.emulators.drive.plant import AxisPlant
from hil.emulators.drive.states import DriveStates
from hil.protocols.cia301 import EMCY_OVERCURRENT, ERR_REG_CURRENT
from hil.protocols.cia402 import (
    CYCLIC_SYNCHRONOUS_POSITION,
    CYCLIC_SYNCHRONOUS_TORQUE,
    MAX_CURRENT,
    MAX_TORQUE,
    MODES_DISPLAY,
    OPERATION_ENABLED,
    RATED_CURRENT,
    TARGET_POSITION,
    TARGET_TORQUE,
)

OVERCURRENT_TRIP = 0x2002  # the emulator's trip level [mA] (manufacturer object)
RATED_KEY, MAX_TORQUE_KEY, MODE_KEY = (RATED_CURRENT, 0), (MAX_TORQUE, 0), (MODES_DISPLAY, 0)
MAX_CURRENT_KEY = (MAX_CURRENT, 0)
TORQUE_KEY, TRIP_KEY = (TARGET_TORQUE, 0), (OVERCURRENT_TRIP, 0)


def wrap_degrees(delta_deg: float) -> float:
    """``delta_deg`` folded into [-180, 180)."""
    return (delta_deg + 180.0) % 360.0 - 180.0


class MotorLoops:
    """The current of each cycle, from the objects, the state and the axis."""

    def __init__(self, values: dict[Key, Any], plant: AxisPlant, config: DriveEmulatorConfig,
                 states: DriveStates) -> None:
        self.values, self.plant, self.config, self.states = values, plant, config, states
        self.last_target_deg: float | None = None

    def forget(self) -> None:
        """The CSP feed-forward starts afresh (after a change of state)."""
        self.last_target_deg = None

    def current_limit_ma(self) -> float:
        """The smallest of 0x6072, 0x6073 (a twin's, when its EDS has it) and the amplifier's."""
        rated = self.values[RATED_KEY]
        per_mille = min(self.values[MAX_TORQUE_KEY], self.values.get(MAX_CURRENT_KEY, math.inf))
        return min(per_mille * rated / 1000.0, self.plant.current_limit_ma)

    def current(self, cycle_s: float) -> tuple[float, bool]:
        """The current the drive applies this cycle and whether it had to limit it."""
        values, states = self.values, self.states
        limit = self.current_limit_ma()
        if states.state == OPERATION_ENABLED:
            mode = values[MODE_KEY]
            if mode == CYCLIC_SYNCHRONOUS_TORQUE:
                wanted = values[TORQUE_KEY] * values[RATED_KEY] / 1000.0
                if abs(wanted) > values[TRIP_KEY]:
                    states.fault(EMCY_OVERCURRENT, ERR_REG_CURRENT)
                    return self.current(cycle_s)  # the fault reaction's current
            elif mode == CYCLIC_SYNCHRONOUS_POSITION:
                wanted = self._position_loop(cycle_s)
            else:
                return 0.0, False
        elif states.ramp_start_ns is not None:
            wanted = self._brake_current(limit)
        else:
            return 0.0, False
        limited = min(max(wanted, -limit), limit)
        return limited, limited != wanted

    def _brake_current(self, limit: float) -> float:
        wanted = -self.config.velocity_gain_ma_per_deg_s * self.plant.velocity_deg_s
        return min(max(wanted, -limit), limit)

    def _position_loop(self, cycle_s: float) -> float:
        """CSP: position P loop with velocity feed-forward (the target's change per cycle)
        around a velocity P loop: the emulated drive's own servo."""
        target_deg = self.values[(TARGET_POSITION, 0)] * 360.0 / self.plant.increments_per_rev
        previous, self.last_target_deg = self.last_target_deg, target_deg
        feed_forward = 0.0 if previous is None else wrap_degrees(target_deg - previous) / cycle_s
        error = wrap_degrees(target_deg - self.plant.position_deg)
        velocity_ref = self.config.position_gain_per_s * error + feed_forward
        return self.config.velocity_gain_ma_per_deg_s * (velocity_ref - self.plant.velocity_deg_s)
