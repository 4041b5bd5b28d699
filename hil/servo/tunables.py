"""The servo run's safety limits as tunable parameters (:mod:`hil.core.tuning`): while a run
runs, each may only be made stricter (:data:`hil.servo.safety.STRICTER`), and
``safety.current_limit_mA`` only lowered, clamping the drive's command from that tick on."""

from __future__ import annotations

from typing import Any

from hil.core.tuning import TunableSpec, Tuner
from hil.drivers.canopen import CanDriveMaster
from hil.servo.safety import STRICTER, SafetyMonitor


def add_safety_limits(tuner: Tuner, safety: SafetyMonitor, master: CanDriveMaster) -> None:
    """Register ``safety.current_limit_mA`` and, when ``[safety]`` is on, its limits."""
    tuner.add(TunableSpec("safety.current_limit_mA", master.current_limit_ma, "mA", 0.0,
                          master.current_limit_ma, None, False, "lower",
                          "what every current command is clamped to"),
              lambda value: _lower_current_limit(master, value))
    if not safety.limits.enabled:
        return
    for name, (unit, stricter, description) in STRICTER.items():
        now = float(getattr(safety.limits, name))
        # the range it may move in: towards the stricter side, positions of either sign
        low = None if stricter == "higher" or name.startswith("position") else 0.0
        high = None if stricter == "higher" else now

        def apply(value: Any, name: str = name) -> None:
            safety.tighten(name, float(value))

        tuner.add(TunableSpec(f"safety.{name}", now, unit, low, high, None, False, stricter,
                              description), apply)


def _lower_current_limit(master: CanDriveMaster, value: Any) -> None:
    master.tighten_current_limit(float(value))
