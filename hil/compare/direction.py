"""Which way a KPI is better, read from its name as its unit is (:func:`hil.core.verdict.unit_of`):
errors, misses, violations, faults, the bench's costs and the computer's times are better lower,
the realtime factor higher; the rest (ticks, currents, switches...) has no better direction. A
``worse:`` tolerance takes its side from here."""

from __future__ import annotations

LOWER = "lower"
HIGHER = "higher"

#: KPIs better higher, by name
HIGHER_IS_BETTER = ("realtime_factor",)
#: KPIs better lower, by name (a group's: every figure in it, ``faults.emcy``, ``step_us.p99``)
LOWER_IS_BETTER = ("faults", "step_us", "solve_ms", "wall_s", "stale_feedback",
                   "clamped_commands", "late_frames", "emcy", "solves_at_limit", "over_limit_s",
                   "overlap_s", "J1_VA", "J2_VA", "SEC_VA", "peak_VA", "energy_VAs")
#: endings and words of a KPI's name that make it better lower
LOWER_IS_BETTER_WORDS = ("error", "misses", "violations", "fallbacks")


def better(name: str) -> str | None:
    """:data:`LOWER` or :data:`HIGHER` for a KPI (nested keys joined by '.', an axis' as
    ``axes.x.max_error_deg``), None when neither is better."""
    parts = name.split(".")
    if any(part in HIGHER_IS_BETTER for part in parts):
        return HIGHER
    if any(part in LOWER_IS_BETTER for part in parts) or \
            any(word in parts[-1] for word in LOWER_IS_BETTER_WORDS):
        return LOWER
    return None
