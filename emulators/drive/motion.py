"""The emulated drive's motion parts shared by its modes: the multi-turn position count
(:class:`PositionCount`, which homing sets), the profile generator (:class:`Profile`: a
trapezoidal move to a position, or a ramp to a velocity, with an acceleration and a
deceleration) and the drive's own loops (:class:`Loops`: a velocity P loop, and a position P
loop with velocity feed-forward around it), in the drive's units: increments, increments/s,
increments/s^2 (one axis turn is ``increments_per_rev``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.objects import Key
from hil.emulators.drive.plant import AxisPlant
from hil.emulators.drive.states import DriveStates
from hil.protocols.cia402 import SW_FOLLOWS_COMMAND


class PositionCount:
    """The axis position in increments, multi-turn: the plant's, moved by ``offset`` (0 at
    power-on; homing sets it so that the home point reads the home offset). The wire
    (0x6064) carries it modulo one turn."""

    def __init__(self, plant: AxisPlant) -> None:
        self.plant = plant
        self.offset = 0

    @property
    def per_turn(self) -> int:
        return self.plant.increments_per_rev

    @property
    def offset_deg(self) -> float:
        """The offset [deg] (0.0 until homed)."""
        return self.offset * 360.0 / self.per_turn

    def counts(self) -> int:
        """The position now [increments, multi-turn]."""
        return math.floor(self.plant.position_deg / 360.0 * self.per_turn) + self.offset

    def exact(self) -> float:
        """The position now [increments, not rounded]."""
        return self.plant.position_deg / 360.0 * self.per_turn + self.offset

    def velocity(self) -> float:
        """The velocity now [increments/s]."""
        return self.plant.velocity_deg_s / 360.0 * self.per_turn

    def now(self) -> tuple[float, float]:
        """:meth:`exact` and :meth:`velocity` in one call (the cyclic path's)."""
        plant = self.plant
        per_turn = plant.increments_per_rev
        return plant.position_deg / 360.0 * per_turn + self.offset, \
            plant.velocity_deg_s / 360.0 * per_turn

    def degrees(self, counts: float) -> float:
        """``counts`` increments [deg] (no offset: a distance or a speed)."""
        return counts * 360.0 / self.per_turn

    def counts_at(self, plant_deg: float) -> float:
        """The count the axis reads at the plant's position ``plant_deg``."""
        return plant_deg / 360.0 * self.per_turn + self.offset

    def set_at(self, plant_deg: float, counts: int) -> None:
        """From now on the plant's position ``plant_deg`` reads ``counts``."""
        self.offset = counts - math.floor(plant_deg / 360.0 * self.per_turn)


@dataclass
class Profile:
    """A profile generator's demand: ``position`` [increments] and ``velocity``
    [increments/s], advanced one cycle at a time by :meth:`move_to` (a trapezoid towards a
    position) or :meth:`ramp_to` (a velocity ramp). Each cycle the velocity changes by at most
    the acceleration (speeding up) or the deceleration (slowing down) times the cycle, and a
    move never exceeds its speed."""

    position: float = 0.0
    velocity: float = 0.0

    def ramp_to(self, velocity: float, acceleration: float, deceleration: float,
                cycle_s: float) -> None:
        """One cycle of a ramp to ``velocity`` (signed)."""
        v = self.velocity
        slowing = abs(velocity) < abs(v) or velocity * v < 0
        step = (deceleration if slowing else acceleration) * cycle_s
        if v * velocity < 0 and abs(v) > step:  # reversing: stop first
            v -= math.copysign(step, v)
        else:
            v += max(-step, min(step, velocity - v))
        self.velocity = v
        self.position += v * cycle_s

    def move_to(self, target: float, speed: float, acceleration: float, deceleration: float,
                cycle_s: float) -> bool:
        """One cycle of a trapezoidal move to ``target`` at up to ``speed``; True once the
        demand stands at the target."""
        remaining = target - self.position
        if remaining == 0.0 and self.velocity == 0.0:
            return True
        direction = 1.0 if remaining > 0 else -1.0
        along = self.velocity * direction  # > 0: moving towards the target
        brake = deceleration * cycle_s
        # the fastest speed from which the deceleration still stops at the target, stepping
        # the position by the velocity of each cycle
        stoppable = (-brake + math.sqrt(brake * brake + 8.0 * deceleration * abs(remaining))) / 2
        speed_up = acceleration if along >= 0 else deceleration
        wanted = min(along + speed_up * cycle_s, speed, stoppable)
        previous, along = along, max(wanted, along - brake)
        if along >= 0 and abs(remaining) <= along * cycle_s and abs(previous) <= brake:
            # there this cycle, from a speed the deceleration stops in one
            self.position, self.velocity = target, 0.0
            return True
        self.velocity = along * direction
        self.position += self.velocity * cycle_s
        return False

    def stop(self, deceleration: float, cycle_s: float) -> bool:
        """One cycle of slowing to a stop; True once standing."""
        self.ramp_to(0.0, deceleration, deceleration, cycle_s)
        return self.velocity == 0.0


class Loops:
    """The drive's own servo loops on the axis, in degrees and mA (the gains of its config):
    the same loops CSP closes."""

    def __init__(self, plant: AxisPlant, config: DriveEmulatorConfig) -> None:
        self.plant, self.config = plant, config

    def velocity(self, velocity_deg_s: float) -> float:
        """The velocity P loop: the current towards ``velocity_deg_s`` [mA]."""
        return self.config.velocity_gain_ma_per_deg_s * (velocity_deg_s
                                                         - self.plant.velocity_deg_s)

    def position(self, error_deg: float, feed_forward_deg_s: float) -> float:
        """The position P loop with velocity feed-forward, around the velocity loop [mA]."""
        return self.velocity(self.config.position_gain_per_s * error_deg + feed_forward_deg_s)


@dataclass
class Axis:
    """What a mode's motion reads and moves: the objects' live values, the plant, the
    config, the position count, the drive's loops, the state machine, the switches."""

    values: dict[Key, Any]
    plant: AxisPlant
    config: DriveEmulatorConfig
    count: PositionCount
    loops: Loops
    states: DriveStates

    def value(self, index: int, subindex: int = 0) -> int:
        """An object's live value (0 when the dictionary, a twin's, lacks it)."""
        value: int = self.values.get((index, subindex), 0)
        return value

    @property
    def standing(self) -> bool:
        return self.states.standing


class ModeMotion:
    """One mode of operation's motion (:mod:`hil.emulators.drive.modes` picks one by the
    mode table): the current it wants each cycle in OPERATION ENABLED, what a controlword
    means to it, and the statusword bits 10, 12 and 13 it sets. By default a cyclic mode:
    bit 12 "follows the command", the demand is the actual position."""

    def __init__(self, axis: Axis) -> None:
        self.axis = axis

    def forget(self) -> None:
        """A change of state or of mode: start afresh from where the axis stands."""

    def controlword(self, controlword: int, previous: int) -> None:
        """A controlword written (SDO) or latched (RPDO) in OPERATION ENABLED."""

    def current(self, cycle_s: float) -> float:
        """The current this cycle [mA], before the current limit."""
        raise NotImplementedError

    def status_bits(self) -> int:
        """Statusword bits 10, 12, 13 in OPERATION ENABLED."""
        return SW_FOLLOWS_COMMAND

    def demand(self) -> tuple[float, float]:
        """The position [increments] and velocity [increments/s] demanded now (0x6062,
        0x606B)."""
        return self.axis.count.now()
