"""KPIs of a bench run (energy paper, sections II and V), accumulated sample by sample.

* ``J1_VA``: the paper's J1, the area under the measured total apparent power over the run
  (VA s; the paper's tables write "VA"). ``energy_VAs`` is the same area under its physical
  name; ``SEC_VA`` (specific energy consumption) is J1 per machine cycle, i.e. per piece.
* ``J2_VA``: the paper's J2, the highest sample of the total apparent power (infinity norm);
  ``peak_VA``: the highest one-second mean of it (what a demand meter integrating over 1 s
  would bill: a short inrush counts for little, a sustained overlap fully).
* ``overlap_s``: time both peripherals were on together (J2 only sees the highest point, so
  overlaps below it cost nothing in the objective: reported, not hidden).
* ``dwell_violations``: relay changes closer than the dwell to the previous change of the same
  relay; ``level_violations``: excursions of a level outside its bounds; ``switches``: relay
  changes per peripheral; ``starts_per_hour``: switch-ons per peripheral per hour of run
  (relay wear, motor starts); ``over_limit_s``: time above the contracted power limit.

Every KPI is a running sum, count or maximum (:class:`BenchKpis`), so a run of any length
keeps the same few numbers; a sample's duration is the time to the next sample (the last one
lasts as long as the one before it).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil.controllers.bench.problem import BenchProblem
from hil.core.kpis import Kpis, kpi


def transitions(on: np.ndarray) -> np.ndarray:
    """Indices where a 0/1 series changes (the index of the first sample of the new state)."""
    on = np.asarray(on).astype(bool)
    return np.nonzero(on[1:] != on[:-1])[0] + 1


@dataclass
class EnergyKpis(Kpis):
    """The energy paper's figures of a run so far: J1 (energy) and J2 (peak) [VA, VAs], the
    specific energy per cycle, overlap, violations, switching."""

    j1_va: float | None = kpi(key="J1_VA")
    j2_va: float | None = kpi(key="J2_VA")
    sec_va: float | None = kpi(key="SEC_VA")
    peak_va: float | None = kpi(key="peak_VA")
    energy_vas: float | None = kpi(key="energy_VAs")
    overlap_s: float | None = kpi()
    dwell_violations: int = kpi(0)
    level_violations: int = kpi(0)
    switches: dict[str, int] | None = kpi()
    starts_per_hour: dict[str, float] | None = kpi()
    over_limit_s: float | None = kpi(optional=True)   # with a peak limit


@dataclass
class BenchRunKpis(EnergyKpis):
    """``hil bench run --json``: the controller and cycles, the energy figures, the
    controller's timing, then context."""

    controller: str = kpi("", limit=False)
    cycles: float = kpi(0.0, limit=False)
    solve_ms: dict[str, float] | None = kpi()
    solves_at_limit: int = kpi(0)
    max_gap: Any = kpi()
    fallbacks: int = kpi(0)
    mcap: str = kpi("", limit=False)
    stop_reason: str | None = kpi(limit=False)
    wall_s: float = kpi(0.0, limit=False)
    realtime_factor: float | None = kpi(limit=False)
    faults: dict[str, Any] | None = kpi(optional=True)   # with a bench link
    disturbed: bool | None = kpi(limit=False, optional=True)

    def document(self) -> dict[str, Any]:
        """The controller and cycles first, as the bench guide lists them."""
        doc = super().document()
        return {"controller": doc.pop("controller"), "cycles": doc.pop("cycles"), **doc}


class _Held:
    """A series of samples, each held until the next: running sums of value x duration."""

    __slots__ = ("count", "first_t", "last_dt", "last_t")

    def __init__(self) -> None:
        self.count = 0
        self.first_t = self.last_t = self.last_dt = 0.0

    def step(self, t_s: float) -> float:
        """Register a sample at ``t_s``; return how long the previous one lasted (0: first)."""
        dt = t_s - self.last_t if self.count else 0.0
        if self.count == 0:
            self.first_t = t_s
        else:
            self.last_dt = dt
        self.count += 1
        self.last_t = t_s
        return dt


class _RelayCount:
    """One relay's changes: switches, switch-ons and changes closer than the dwell."""

    __slots__ = ("changes", "dwell_violations", "first_on", "last_change_t", "on", "ons")

    def __init__(self) -> None:
        self.on: bool | None = None
        self.first_on = False
        self.changes = self.ons = self.dwell_violations = 0
        self.last_change_t: float | None = None

    def sample(self, t_s: float, on: bool, min_spacing_s: float) -> None:
        if self.on is None:
            self.on = self.first_on = on
            self.ons = int(on)
            return
        if on == self.on:
            return
        self.on = on
        self.changes += 1
        self.ons += on
        if self.last_change_t is not None and t_s - self.last_change_t < min_spacing_s:
            self.dwell_violations += 1
        self.last_change_t = t_s


class BenchKpis:
    """A bench run's KPIs in constant memory: feed every good meter sample to :meth:`power`,
    the relays of every sample to :meth:`relays`, every good level reading to :meth:`levels`,
    then ask :meth:`kpis`. ``sample_period_s`` sets the one-second window of ``peak_VA``."""

    def __init__(self, problem: BenchProblem, *, sample_period_s: float,
                 limit_va: float | None = None, dwell_tol_s: float = 0.005) -> None:
        self.problem, self.limit_va, self.dwell_tol_s = problem, limit_va, dwell_tol_s
        self._power, self._relays_t = _Held(), _Held()
        self._energy = self._over_limit = self._overlap = 0.0
        self._s_last = self._s_max = 0.0
        self._window = np.zeros(max(1, round(1.0 / sample_period_s)))  # last 1 s of samples
        self._window_sum = self._window_peak = 0.0
        self._both_on = False
        self._relay = {n: _RelayCount() for n in problem.peripherals}
        self._outside: dict[str, bool] = {}
        self._excursions = {r.name: 0 for r in problem.resources}
        self._bounds = {r.name: (r.q_min, r.q_max) for r in problem.resources}
        self.level_samples = 0

    @property
    def power_samples(self) -> int:
        return self._power.count

    def power(self, t_s: float, s_va: float) -> None:
        """A good meter sample: total apparent power ``s_va`` at ``t_s``."""
        previous = self._s_last
        dt = self._power.step(t_s)
        self._energy += previous * dt
        if self.limit_va is not None and previous > self.limit_va:
            self._over_limit += dt
        self._s_last = s_va
        n = self._power.count
        self._s_max = s_va if n == 1 else max(self._s_max, s_va)
        window = self._window
        slot = (n - 1) % window.size
        if slot == 0:  # once per window: a fresh sum, so rounding errors do not pile up
            self._window_sum = float(window[1:].sum())
        else:
            self._window_sum -= window[slot]
        window[slot] = s_va
        self._window_sum += s_va
        if n >= window.size:
            self._window_peak = max(self._window_peak, self._window_sum / window.size)

    def relays(self, t_s: float, on: Mapping[str, bool]) -> None:
        """The relays of one sample at ``t_s`` (every peripheral named)."""
        dt = self._relays_t.step(t_s)
        if self._both_on:
            self._overlap += dt
        names = self.problem.peripherals
        self._both_on = len(names) > 1 and all(on[n] for n in names)
        for name in names:
            self._relay[name].sample(t_s, bool(on[name]),
                                     self.problem.dwell_s[name] - self.dwell_tol_s)

    def levels(self, t_s: float, levels: Mapping[str, float]) -> None:
        """A good reading of the resource levels at ``t_s``."""
        self.level_samples += 1
        for name, (low, high) in self._bounds.items():
            if name not in levels:
                continue
            q = levels[name]
            outside = q < low or q > high
            if outside and not self._outside.get(name, False):
                self._excursions[name] += 1
            self._outside[name] = outside

    def kpis(self, cycles: float) -> EnergyKpis:
        """The energy KPIs of the run so far (needs at least one meter sample)."""
        if self._power.count == 0:
            raise ValueError("no meter sample: no bench KPIs")
        last_dt = self._power.last_dt
        energy = self._energy + self._s_last * last_dt
        names = self.problem.peripherals
        relays_last_dt = self._relays_t.last_dt
        overlap = self._overlap + (relays_last_dt if self._both_on else 0.0)
        window = self._window
        n = self._power.count
        peak = (self._s_max if n < 2 else
                self._window_peak if n >= window.size else float(window[:n].mean()))
        held = self._relays_t
        hours = max(held.last_t - held.first_t, 1e-9) / 3600.0 if held.count else 0.0
        over = None
        if self.limit_va is not None:
            over = round(self._over_limit + (last_dt if self._s_last > self.limit_va else 0.0),
                         2)
        return EnergyKpis(
            j1_va=round(energy, 1), j2_va=round(self._s_max, 2),
            sec_va=round(energy / cycles, 1) if cycles else None, peak_va=round(peak, 2),
            energy_vas=round(energy, 1), overlap_s=round(overlap, 2),
            dwell_violations=sum(self._relay[n].dwell_violations for n in names),
            level_violations=sum(self._excursions.values()),
            switches={n: self._relay[n].changes + int(self._relay[n].first_on) for n in names},
            starts_per_hour={n: round(self._relay[n].ons / hours, 1) if hours else 0.0
                             for n in names},
            over_limit_s=over)


def timing_summary(samples_ms: Sequence[float]) -> dict[str, float]:
    """{median, p99, max} of decision times in ms (zeros when there are none)."""
    x = np.asarray(samples_ms, float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"median": 0.0, "p99": 0.0, "max": 0.0}
    return {"median": round(float(np.median(x)), 3),
            "p99": round(float(np.percentile(x, 99)), 3),
            "max": round(float(x.max()), 3)}
