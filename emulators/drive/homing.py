"""Homing mode (HM): the CiA 402 homing methods of :data:`hil.protocols.cia402.HOMING_METHODS`
on the axis' simulated switches and index pulse (:mod:`hil.emulators.drive.switches`).

A rising edge of controlword bit 4 starts the method 0x6098; its falling edge or bit 8 (halt)
interrupts it. A method with a limit switch searches it at the switch-search speed 0x6099:1,
then leaves it the other way at the zero-search speed 0x6099:2: home is the switch's edge, or
(methods 1, 2) the first index pulse after it. Methods 33 and 34 search the index pulse at the
zero-search speed; 35 and 37 take the position where the axis stands. Every speed changes at
the homing acceleration 0x609A. At home the position count becomes the home offset 0x607C,
and the axis goes back to the home point.

Statusword (CiA 402): bit 12 homing attained, bit 10 target reached (standing at home, or
standing after an interruption or an error), bit 13 homing error: a limit switch met while
moving towards it where the method looks for something else, or nothing found within
``[emulator] homing_search_deg`` of where the search began. An error stops the axis."""

from __future__ import annotations

from enum import Enum

from hil.emulators.drive.motion import Axis, ModeMotion, Profile
from hil.protocols.cia402 import (
    CW_HALT,
    CW_HOMING_START,
    DI_NEGATIVE_LIMIT,
    DI_POSITIVE_LIMIT,
    HOME_OFFSET,
    HOMING_ACCELERATION,
    HOMING_METHOD,
    HOMING_METHODS,
    HOMING_SPEEDS,
    POSITION_WINDOW,
    SW_HOMING_ATTAINED,
    SW_HOMING_ERROR,
    SW_TARGET_REACHED,
    HomingMethod,
)


class Phase(Enum):
    IDLE = "not started or interrupted"
    SEARCH = "searching the switch"
    LEAVE = "leaving the switch"
    INDEX = "searching the index pulse"
    RETURN = "going back to the home point"
    DONE = "homed"
    ERROR = "homing error"


MOVING = (Phase.SEARCH, Phase.LEAVE, Phase.INDEX)
LIMIT_AHEAD = {-1: DI_NEGATIVE_LIMIT, +1: DI_POSITIVE_LIMIT}  # the limit a direction meets


class Homing(ModeMotion):
    """HM's method run (see the module)."""

    def __init__(self, axis: Axis) -> None:
        super().__init__(axis)
        self.phase = Phase.IDLE
        self.attained = False
        self.forget()

    def forget(self) -> None:
        """Standing, not homing (homed stays homed: the count keeps its home)."""
        count = self.axis.count
        self.profile = Profile(count.exact(), 0.0)
        if self.phase is not Phase.DONE:
            self.phase = Phase.IDLE
        self.method: HomingMethod | None = None
        self.direction = 0
        self.start_deg = self.previous_deg = 0.0  # where the search began, the last cycle
        self.home_count = 0.0

    def controlword(self, controlword: int, previous: int) -> None:
        started = controlword & CW_HOMING_START and not previous & CW_HOMING_START
        stopped = (controlword & CW_HALT) or (previous & CW_HOMING_START
                                              and not controlword & CW_HOMING_START)
        if started and not controlword & CW_HALT:
            self._start(HOMING_METHODS.get(self.axis.value(HOMING_METHOD)))
        elif stopped and self.phase in (*MOVING, Phase.RETURN):
            self.phase = Phase.IDLE

    def _start(self, method: HomingMethod | None) -> None:
        plant = self.axis.plant
        self.method, self.attained = method, False
        self.profile = Profile(self.axis.count.exact(), 0.0)
        self.start_deg = self.previous_deg = plant.position_deg
        if method is None:  # 0x6098 holds no method hil knows (0: none)
            self.phase = Phase.ERROR
        elif method.direction == 0:  # the current position is home
            self._home_at(plant.position_deg)
        elif method.switch:
            self._search(Phase.SEARCH, method.direction)
        else:
            self._search(Phase.INDEX, method.direction)

    def _search(self, phase: Phase, direction: int) -> None:
        self.phase, self.direction = phase, direction

    def _home_at(self, plant_deg: float) -> None:
        """Home found at the plant's ``plant_deg``: it reads the home offset from now on."""
        count = self.axis.count
        before = count.offset
        count.set_at(plant_deg, self.axis.value(HOME_OFFSET))
        self.profile.position += count.offset - before
        self.home_count = count.counts_at(plant_deg)
        self.attained = True
        self.phase = Phase.RETURN

    def current(self, cycle_s: float) -> float:
        axis, profile = self.axis, self.profile
        acceleration = axis.value(HOMING_ACCELERATION)
        if self.phase in MOVING:
            speed = axis.value(HOMING_SPEEDS, 1 if self.phase is Phase.SEARCH else 2)
            profile.ramp_to(self.direction * speed, acceleration, acceleration, cycle_s)
            self._look()
        elif self.phase is Phase.RETURN:
            at_home = profile.move_to(self.home_count, axis.value(HOMING_SPEEDS, 2),
                                      acceleration, acceleration, cycle_s)
            if at_home and abs(self.home_count - axis.count.exact()) <= \
                    axis.value(POSITION_WINDOW) and axis.standing:
                self.phase = Phase.DONE
        else:
            profile.stop(acceleration, cycle_s)
        actual = axis.count.exact()
        return axis.loops.position(axis.count.degrees(profile.position - actual),
                                   axis.count.degrees(profile.velocity))

    def _look(self) -> None:
        """What the axis met this cycle, heading in the phase's direction."""
        axis, method = self.axis, self.method
        assert method is not None
        switches, plant = axis.config.switches, axis.plant
        position = plant.position_deg
        inputs = switches.inputs(position)
        if self.phase is Phase.SEARCH and inputs & method.switch:
            self._search(Phase.LEAVE, -self.direction)
            return
        if self.phase is Phase.LEAVE and not inputs & method.switch:
            edge = switches.edge(method.switch)
            if method.index:
                self.start_deg = self.previous_deg = edge
                self._search(Phase.INDEX, self.direction)
            else:
                self._home_at(edge)
            return
        if self.phase is Phase.INDEX:
            pulse = switches.index_between(self.previous_deg, position)
            self.previous_deg = position
            if pulse is not None:
                self._home_at(pulse)
                return
        ahead = LIMIT_AHEAD[self.direction]
        wrong_limit = inputs & ahead and not (self.phase is Phase.SEARCH
                                              and ahead == method.switch)
        if wrong_limit or abs(position - self.start_deg) > axis.config.homing_search_deg:
            self.phase = Phase.ERROR

    def status_bits(self) -> int:
        standing = self.axis.standing
        if self.phase is Phase.ERROR:
            return SW_HOMING_ERROR | (SW_TARGET_REACHED if standing else 0)
        if self.phase is Phase.DONE:
            return SW_HOMING_ATTAINED | SW_TARGET_REACHED
        if self.phase is Phase.IDLE:
            return SW_TARGET_REACHED if standing else 0
        return SW_HOMING_ATTAINED if self.attained else 0

    def demand(self) -> tuple[float, float]:
        return self.profile.position, self.profile.velocity
