"""The bench run's safety limits, on by default (bench.toml ``[safety]``): whatever the
controller does, the bench is not held above a power ceiling nor a resource outside its
physical range.

Checked every sample (record phase), after the sampler's reading; the first limit crossed is
recorded as a ``safety.stop`` event and stops the loop, whose stop drives every relay to its
safe level; the run then ends with :class:`SafetyStopError` (exit 2) naming the limit:

* the meter's ``total_va`` above ``max_total_va`` for longer than ``max_total_va_ms`` (a
  motor's inrush is shorter than that);
* a resource level outside ``[level_min, level_max]``.

Non-finite readings never reach this check: the sampler counts them as faults first.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Protocol

from hil.core.loop import Task

if TYPE_CHECKING:
    from hil.core.session import Session


class Readings(Protocol):
    """What the check reads: the sampler's readings of this sample (None: none came)."""

    divisor: int
    fresh_power: dict[str, float] | None
    fresh_levels: dict[str, float] | None



@dataclass(frozen=True)
class BenchSafety:
    """The limits of ``[safety]`` (``enabled = false`` switches every one off)."""

    enabled: bool = True
    max_total_va: float = 1200.0
    max_total_va_ms: float = 500.0
    level_min: float = 0.0
    level_max: float = 250.0


#: the limits of ``[safety]`` that may change while a run runs, each only the stricter way:
#: name -> (unit, "lower" or "higher", what it is)
STRICTER: dict[str, tuple[str, str, str]] = {
    "max_total_va": ("VA", "lower", "the highest total apparent power allowed"),
    "max_total_va_ms": ("ms", "lower", "how long the power may stay above it"),
    "level_min": ("", "higher", "the lowest resource level allowed"),
    "level_max": ("", "lower", "the highest resource level allowed"),
}


class BenchSafetyTask(Task):
    """Every sample (record phase): the limits of :class:`BenchSafety` on the sampler's new
    reading; ``stopped`` holds the first one crossed, as one line."""

    def __init__(self, limits: BenchSafety, sampler: Readings, session: Session,
                 period_s: float, clock_origin: Callable[[], int]) -> None:
        super().__init__("safety", sampler.divisor)
        self.limits, self.sampler, self.session = limits, sampler, session
        self._origin = clock_origin
        self._period_s = period_s
        self._window_samples = max(1, round(limits.max_total_va_ms / 1000 / period_s))
        self._over = 0
        self.stopped: str | None = None

    def record(self, t_ns: int) -> None:
        if not self.limits.enabled or self.stopped is not None:
            return
        found = self._check(self.sampler.fresh_power, self.sampler.fresh_levels)
        if found is not None:
            t_s = (t_ns - self._origin()) / 1e9
            self.stopped = f"safety stop at t={t_s:.2f} s: {found}"
            self.session.event("safety.stop", self.stopped, level="error", source="safety")
            self.session.loop.stop(self.stopped)

    def tighten(self, name: str, value: float) -> None:
        """Make the limit ``name`` (a field of :class:`BenchSafety`) ``value`` from this tick
        on; the tuner lets it move only the stricter way (:data:`STRICTER`)."""
        changed: dict[str, Any] = {name: value}
        self.limits = replace(self.limits, **changed)
        self._window_samples = max(1, round(self.limits.max_total_va_ms / 1000
                                            / self._period_s))

    def _check(self, power: dict[str, float] | None, levels: dict[str, float] | None
               ) -> str | None:
        limits = self.limits
        if power is not None and "total_va" in power:
            total = power["total_va"]
            self._over = self._over + 1 if total > limits.max_total_va else 0
            if self._over > self._window_samples:
                return (f"total_va {total:.1f} VA above {limits.max_total_va:g} VA for more "
                        f"than {limits.max_total_va_ms:g} ms")
        for name, value in (levels or {}).items():
            if not limits.level_min <= value <= limits.level_max:
                return (f"level {name} = {value:.2f} outside its physical range "
                        f"[{limits.level_min:g}, {limits.level_max:g}]")
        return None
