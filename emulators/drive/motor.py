"""The emulated drive's current loops: the current it applies each cycle, in its state and
mode - in OPERATION ENABLED the motion of the mode in 0x6061 (:mod:`hil.emulators.drive.modes`),
in a ramp (quick stop, fault reaction) its velocity loop braking at the current limit - and
whether it had to limit it (statusword bit 11)."""

from __future__ import annotations

import math
from typing import Any

from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.modes import mode_motions
from hil.emulators.drive.motion import Axis, Loops, ModeMotion, PositionCount
from hil.emulators.drive.objects import Key
from hil.emulators.drive.plant import AxisPlant
from hil.emulators.drive.states import DriveStates
from hil.protocols.cia402 import (
    MAX_CURRENT,
    MAX_TORQUE,
    MODES_DISPLAY,
    OPERATION_ENABLED,
    RATED_CURRENT,
    SW_FOLLOWS_COMMAND,
)

RATED_KEY, MAX_TORQUE_KEY, MODE_KEY = (RATED_CURRENT, 0), (MAX_TORQUE, 0), (MODES_DISPLAY, 0)
MAX_CURRENT_KEY = (MAX_CURRENT, 0)


class MotorLoops:
    """The current of each cycle, from the objects, the state and the axis; ``count`` the
    axis' position in increments (multi-turn, homing sets it)."""

    def __init__(self, values: dict[Key, Any], plant: AxisPlant, config: DriveEmulatorConfig,
                 states: DriveStates) -> None:
        self.values, self.plant, self.config, self.states = values, plant, config, states
        self.count = PositionCount(plant)
        self._axis = Axis(values, plant, config, self.count, Loops(plant, config), states)
        self.motions = mode_motions(self._axis)
        states.mode_bits = self.status_bits

    def reset(self) -> None:
        """Power-on: the count as the plant's (not homed), every mode from its start."""
        self.count.offset = 0
        self.motions = mode_motions(self._axis)

    def motion(self) -> ModeMotion | None:
        """The motion of the mode in effect (None: no mode)."""
        return self.motions.get(self.values[MODE_KEY])

    def forget(self) -> None:
        """Every mode starts afresh (after a change of state or of mode)."""
        for motion in self.motions.values():
            motion.forget()

    def controlword(self, controlword: int, previous: int) -> None:
        """A controlword applied: what it means to the mode in effect, when enabled."""
        motion = self.motion()
        if motion is not None and self.states.state == OPERATION_ENABLED:
            motion.controlword(controlword, previous)

    def status_bits(self) -> int:
        """Statusword bits 10, 12, 13 of the mode in effect."""
        motion = self.motions.get(self.values[MODE_KEY])
        return SW_FOLLOWS_COMMAND if motion is None else motion.status_bits()

    def demand(self) -> tuple[float, float]:
        """The position [increments] and velocity [increments/s] demanded now."""
        motion = self.motions.get(self.values[MODE_KEY])
        if motion is None or self.states.state != OPERATION_ENABLED:
            return self.count.now()
        return motion.demand()

    def current_limit_ma(self) -> float:
        """The smallest of 0x6072, 0x6073 (a twin's, when its EDS has it) and the amplifier's."""
        rated = self.values[RATED_KEY]
        per_mille = min(self.values[MAX_TORQUE_KEY], self.values.get(MAX_CURRENT_KEY, math.inf))
        return min(per_mille * rated / 1000.0, self.plant.current_limit_ma)

    def current(self, cycle_s: float) -> tuple[float, bool]:
        """The current the drive applies this cycle and whether it had to limit it."""
        states = self.states
        limit = self.current_limit_ma()
        if states.state == OPERATION_ENABLED:
            motion = self.motions.get(self.values[MODE_KEY])
            if motion is None:
                return 0.0, False
            wanted = motion.current(cycle_s)
            if states.state != OPERATION_ENABLED:  # the motion faulted the drive
                return self.current(cycle_s)  # the fault reaction's current
        elif states.ramp_start_ns is not None:
            wanted = self._brake_current(limit)
        else:
            return 0.0, False
        limited = min(max(wanted, -limit), limit)
        return limited, limited != wanted

    def _brake_current(self, limit: float) -> float:
        wanted = -self.config.velocity_gain_ma_per_deg_s * self.plant.velocity_deg_s
        return min(max(wanted, -limit), limit)
