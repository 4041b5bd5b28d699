"""The servo run's safety limits as tunable parameters (:mod:`hil.core.tuning`): while a run
runs, each may only be made stricter (:data:`hil.servo.safety.STRICTER`), and
``safety.current_limit_mA`` only lowered, clamping the drive's command from that tick on."""

from __future__ import annotations

from typing import Any

from hil.core.tuning import TunableSpec, Tuner, add_safety_limits
from hil.drivers.canopen import CanDriveMaster
from hil.servo.safety import STRICTER, SafetyMonitor


def add_servo_limits(tuner: Tuner, safety: SafetyMonitor, master: CanDriveMaster) -> None:
    """Register ``safety.current_limit_mA`` and, when ``[safety]`` is on, its limits."""
    tuner.add(TunableSpec("safety.current_limit_mA", master.current_limit_ma, "mA", 0.0,
                          master.current_limit_ma, None, False, "lower",
                          "what every current command is clamped to"),
              lambda value: _lower_current_limit(master, value))
    if safety.limits.enabled:
        add_safety_limits(tuner, safety.limits, STRICTER, safety.tighten, signed="position")


def _lower_current_limit(master: CanDriveMaster, value: Any) -> None:
    master.tighten_current_limit(float(value))
