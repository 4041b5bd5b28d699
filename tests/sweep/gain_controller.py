"""A servo controller for the sweep tests: current = gain * error; a negative gain is refused
when the controller is built, as a user's controller refuses a bad parameter."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


class Gain:
    def __init__(self, reference: Any, params: Mapping[str, Any]) -> None:
        self.reference = reference
        self.gain = float(params.get("gain", 300.0))
        if self.gain < 0:
            raise ValueError(f"gain must be >= 0, got {self.gain:g}")

    def step(self, position_deg: float, t_s: float) -> float:
        error = (float(self.reference.position(t_s)) - position_deg + 180.0) % 360.0 - 180.0
        return self.gain * error
