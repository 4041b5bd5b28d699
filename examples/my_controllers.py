"""Two controllers a user might bring to hil: they need nothing from hil but its contracts.

Run them with the command line::

    hil bench run --controller examples/my_controllers.py:ThresholdRelays --param on_below=75
    hil servo run --controller examples/my_controllers.py:PdPosition --param kp=400 --duration 2

or from Python and pytest (``examples/test_my_controllers.py``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any


class ThresholdRelays:
    """A bench controller: run a peripheral while its resource is low, stop it when full.

    Params: ``on_below`` and ``off_above`` (levels, default 75 and 130) and ``pairs`` (which
    relay fills which resource, default ``{"q1": "P1", "q2": "P2"}``). The bench's safety
    layer still holds every relay's minimum on/off time, whatever this asks.
    """

    def __init__(self, params: Mapping[str, Any]) -> None:
        self.on_below = float(params.get("on_below", 75.0))
        self.off_above = float(params.get("off_above", 130.0))
        self.pairs = dict(params.get("pairs", {"q1": "P1", "q2": "P2"}))
        if not self.on_below < self.off_above:
            raise ValueError(f"on_below ({self.on_below}) must be below off_above "
                             f"({self.off_above})")

    def decide(self, obs: Any) -> dict[str, bool]:
        """``obs.levels`` {"q1": ..}, ``obs.relays`` {"P1": ..}; returns the relays to set."""
        command = {}
        for level, relay in self.pairs.items():
            q = obs.levels[level]
            if q < self.on_below:
                command[relay] = True
            elif q > self.off_above:
                command[relay] = False
        return command


class PdPosition:
    """A servo controller: proportional-derivative on the tracking error, every tick.

    Params: ``kp`` [mA/deg], ``kd`` [mA s/deg] and ``umax`` [mA] (default 300, 6, 1000).
    The drive's driver clamps the current to its configured limit as well.
    """

    def __init__(self, reference: Any, params: Mapping[str, Any]) -> None:
        self.reference = reference
        self.kp = float(params.get("kp", 300.0))
        self.kd = float(params.get("kd", 6.0))
        self.umax = float(params.get("umax", 1000.0))
        self.reset()

    def reset(self) -> None:
        self._last: tuple[float, float] | None = None

    def step(self, position_deg: float, t_s: float) -> float:
        target = float(self.reference.position(t_s))
        error = (target - position_deg + 180.0) % 360.0 - 180.0
        rate = 0.0
        if self._last is not None and t_s > self._last[0]:
            rate = (error - self._last[1]) / (t_s - self._last[0])
        self._last = (t_s, error)
        current = self.kp * error + self.kd * rate
        return math.copysign(min(abs(current), self.umax), current)
