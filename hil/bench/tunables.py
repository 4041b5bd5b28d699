"""The bench run's safety limits as tunable parameters (:mod:`hil.core.tuning`): while a run
runs, each may only be made stricter (:data:`hil.bench.safety.STRICTER`)."""

from __future__ import annotations

from hil.bench.safety import STRICTER, BenchSafetyTask
from hil.core.tuning import Tuner, add_safety_limits


def add_bench_limits(tuner: Tuner, safety: BenchSafetyTask) -> None:
    """Register the limits of ``[safety]`` as ``safety.NAME`` (none when it is off)."""
    if safety.limits.enabled:
        add_safety_limits(tuner, safety.limits, STRICTER, safety.tighten, signed="level")
