"""The bench run's safety limits as tunable parameters (:mod:`hil.core.tuning`): while a run
runs, each may only be made stricter (:data:`hil.bench.safety.STRICTER`)."""

from __future__ import annotations

from typing import Any

from hil.bench.safety import STRICTER, BenchSafetyTask
from hil.core.tuning import TunableSpec, Tuner


def add_safety_limits(tuner: Tuner, safety: BenchSafetyTask) -> None:
    """Register the limits of ``[safety]`` as ``safety.NAME`` (none when it is off)."""
    if not safety.limits.enabled:
        return
    for name, (unit, stricter, description) in STRICTER.items():
        now = float(getattr(safety.limits, name))
        low = None if stricter == "higher" or name.startswith("level") else 0.0
        high = None if stricter == "higher" else now

        def apply(value: Any, name: str = name) -> None:
            safety.tighten(name, float(value))

        tuner.add(TunableSpec(f"safety.{name}", now, unit, low, high, None, False, stricter,
                              description), apply)
