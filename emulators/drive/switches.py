"""The emulated axis' switches and encoder index (``[emulator]`` of drive.toml): a negative and
a positive limit switch, a home switch and the index pulse, at positions in degrees of the
axis from where it stood at power-on, as digital inputs 0x60FD and as homing finds them."""

from __future__ import annotations

import math
from dataclasses import dataclass

from hil.protocols.cia402 import DI_HOME_SWITCH, DI_NEGATIVE_LIMIT, DI_POSITIVE_LIMIT


@dataclass(frozen=True)
class Switches:
    """The negative limit switch is on at and below ``negative_limit_deg``, the positive one
    at and above ``positive_limit_deg``, the home switch at and above ``home_switch_deg``;
    the index pulse comes at ``index_pulse_deg`` and every ``index_period_deg`` (one motor
    revolution) from there."""

    negative_limit_deg: float = -190.0
    positive_limit_deg: float = 190.0
    home_switch_deg: float = 90.0
    index_pulse_deg: float = 180.0
    index_period_deg: float = 360.0

    def inputs(self, position_deg: float) -> int:
        """0x60FD at ``position_deg``: bit 0 negative limit, 1 positive limit, 2 home."""
        bits = 0
        if position_deg <= self.negative_limit_deg:
            bits |= DI_NEGATIVE_LIMIT
        if position_deg >= self.positive_limit_deg:
            bits |= DI_POSITIVE_LIMIT
        if position_deg >= self.home_switch_deg:
            bits |= DI_HOME_SWITCH
        return bits

    def edge(self, switch: int) -> float:
        """Where ``switch`` (a DI_* bit) turns on or off [deg]."""
        return {DI_NEGATIVE_LIMIT: self.negative_limit_deg,
                DI_POSITIVE_LIMIT: self.positive_limit_deg,
                DI_HOME_SWITCH: self.home_switch_deg}[switch]

    def index_between(self, start_deg: float, end_deg: float) -> float | None:
        """The index pulse the axis passed moving from ``start_deg`` to ``end_deg`` (the one
        nearest ``start_deg``, ``end_deg`` included, ``start_deg`` not), or None."""
        period, phase = self.index_period_deg, self.index_pulse_deg
        if end_deg > start_deg:
            pulse = phase + period * (math.floor((start_deg - phase) / period) + 1)
            return pulse if pulse <= end_deg else None
        if end_deg < start_deg:
            pulse = phase + period * (math.ceil((start_deg - phase) / period) - 1)
            return pulse if pulse >= end_deg else None
        return None
