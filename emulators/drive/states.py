"""The emulated drive's CiA 402 state machine (the tables of :mod:`hil.protocols.cia402`): the
statusword of each state, the transitions a controlword makes, quick stop and fault reaction
(brake to standstill, at most the quick-stop time-out), a fault reset on the rising edge of
bit 7."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from hil.emulators.drive.objects import Key
from hil.emulators.drive.plant import AxisPlant
from hil.protocols.cia301 import EMCY_RESET, ERROR_REGISTER
from hil.protocols.cia402 import (
    CONTROLWORD,
    ERROR_CODE,
    FAULT,
    FAULT_REACTION_ACTIVE,
    FAULT_RESET,
    NOT_READY_TO_SWITCH_ON,
    OPERATION_ENABLED,
    QUICK_STOP_ACTIVE,
    QUICK_STOP_OPTION,
    QUICK_STOP_STAYS,
    QUICK_STOP_THEN_DISABLED,
    STATUSWORD_MASKS,
    SW_FOLLOWS_COMMAND,
    SW_INTERNAL_LIMIT,
    SW_REMOTE,
    SW_VOLTAGE_ENABLED,
    SW_WARNING,
    SWITCH_ON_DISABLED,
    TRANSITIONS,
    command_of,
)

log = logging.getLogger(__name__)

# The statusword of each CiA 402 state: its bits of the profile, plus bit 9 (remote) always and
# bit 4 (voltage enabled) whenever the emulated DC link is up (every state after power-on).
STATUSWORD = {state: (value | SW_REMOTE | SW_VOLTAGE_ENABLED) if state != NOT_READY_TO_SWITCH_ON
              else value for state, (_mask, value) in STATUSWORD_MASKS.items()}
POWERED = (OPERATION_ENABLED, QUICK_STOP_ACTIVE, FAULT_REACTION_ACTIVE)
DISABLE_AT_ONCE = 0  # quick stop option 0: disable the drive function at once


class DriveStates:
    """The state, the last controlword, a ramp in progress (quick stop or fault reaction) and
    the warning bits. ``emcy(code, register, manufacturer)`` reports; ``entered(state)`` runs
    after every change of state (the node's own consequences)."""

    def __init__(self, values: dict[Key, Any], plant: AxisPlant, standstill_deg_s: float,
                 now: Callable[[], int], emcy: Callable[[int, int, bytes], None],
                 entered: Callable[[str], None]) -> None:
        self.values, self.plant, self.standstill_deg_s = values, plant, standstill_deg_s
        self._now, self._emcy, self._entered = now, emcy, entered
        #: statusword bits 10, 12, 13 in OPERATION ENABLED: the mode's (the node sets it)
        self.mode_bits: Callable[[], int] = lambda: SW_FOLLOWS_COMMAND
        self.reset()

    def reset(self) -> None:
        """Power-on: NOT READY TO SWITCH ON, nothing in progress."""
        self.state = NOT_READY_TO_SWITCH_ON
        self.controlword = 0
        self.ramp_start_ns: int | None = None
        self.limit_active = False   # the current was limited this cycle (bit 11)
        self.comm_warning = False   # a lost master or SYNC while no torque was on (bit 7)

    @property
    def statusword(self) -> int:
        state = self.state
        word = STATUSWORD[state]
        if state == OPERATION_ENABLED:
            word |= self.mode_bits()
            if self.limit_active:
                word |= SW_INTERNAL_LIMIT
        if self.comm_warning and state not in (FAULT, FAULT_REACTION_ACTIVE):
            word |= SW_WARNING
        return word

    @property
    def standing(self) -> bool:
        return abs(self.plant.velocity_deg_s) < self.standstill_deg_s

    def enter(self, state: str) -> None:
        if state == self.state:
            return
        log.debug("emulated drive: %s -> %s", self.state, state)
        self.state = state
        if state not in (QUICK_STOP_ACTIVE, FAULT_REACTION_ACTIVE):
            self.ramp_start_ns = None
        if state not in POWERED:
            self.plant.applied_current_ma = 0.0
        self._entered(state)

    def apply_controlword(self, cw: int) -> None:
        """One controlword write (SDO) or latch (RPDO on SYNC): the transitions its command
        makes from the current state (:data:`hil.protocols.cia402.TRANSITIONS`)."""
        previous, self.controlword = self.controlword, cw
        self.values[(CONTROLWORD, 0)] = cw
        command = command_of(cw, previous)
        if command is None:
            return
        for number, state in TRANSITIONS.get((self.state, command), ()):
            if number == 16 and self.values[(QUICK_STOP_OPTION, 0)] not in QUICK_STOP_STAYS:
                return
            if command == FAULT_RESET:
                self.clear_errors()
            if state == QUICK_STOP_ACTIVE:
                self.start_quick_stop()
            else:
                self.enter(state)

    def start_quick_stop(self) -> None:
        self.enter(QUICK_STOP_ACTIVE)
        if self.values[(QUICK_STOP_OPTION, 0)] == DISABLE_AT_ONCE:
            self.enter(SWITCH_ON_DISABLED)
            return
        self.ramp_start_ns = self._now()
        if self.standing:
            self.ramp_finished()

    def ramp_finished(self) -> None:
        """Standstill reached (or the ramp timed out): torque off where the option says so."""
        self.ramp_start_ns = None
        if self.state == FAULT_REACTION_ACTIVE:
            self.enter(FAULT)  # 14
        elif self.state == QUICK_STOP_ACTIVE and \
                self.values[(QUICK_STOP_OPTION, 0)] in QUICK_STOP_THEN_DISABLED:
            self.enter(SWITCH_ON_DISABLED)  # 12
        self.plant.applied_current_ma = 0.0

    def fault(self, code: int, register: int, cause: int = 0) -> None:
        """A fault: EMCY, then the fault reaction (13), then FAULT (14) at standstill."""
        if self.state in (FAULT, FAULT_REACTION_ACTIVE):
            return
        self.values[(ERROR_CODE, 0)] = code
        self._emcy(code, register, bytes([cause]) if cause else b"")
        self.enter(FAULT_REACTION_ACTIVE)
        self.ramp_start_ns = self._now()
        if self.standing:
            self.ramp_finished()

    def clear_errors(self) -> None:
        self.values[(ERROR_CODE, 0)] = 0
        self.values[(ERROR_REGISTER, 0)] = 0
        self.comm_warning = False
        self._emcy(EMCY_RESET, 0, b"")
