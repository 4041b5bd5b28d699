"""KPIs of a bench run (energy paper, sections II and V), from the recorded signals.

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
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from controllers.bench_problem import BenchProblem


def transitions(on: np.ndarray) -> np.ndarray:
    """Indices where a 0/1 series changes (the index of the first sample of the new state)."""
    on = np.asarray(on).astype(bool)
    return np.nonzero(on[1:] != on[:-1])[0] + 1


def switch_ons(on: np.ndarray) -> int:
    """Off-to-on changes of a 0/1 series (one more if it starts on)."""
    on = np.asarray(on).astype(bool)
    return int(np.sum(on[1:] & ~on[:-1]) + (1 if on.size and on[0] else 0))


def dwell_violations(t_s: np.ndarray, on: np.ndarray, dwell_s: float, tol_s: float) -> int:
    """Changes of one relay that came less than ``dwell_s - tol_s`` after its previous one."""
    changes = t_s[transitions(on)]
    return int(np.sum(np.diff(changes) < dwell_s - tol_s))


def excursions(q: np.ndarray, low: float, high: float) -> int:
    """How many times the level left ``[low, high]``."""
    outside = (np.asarray(q) < low) | (np.asarray(q) > high)
    return int(outside[0]) + int(np.sum(outside[1:] & ~outside[:-1]))


def one_second_peak(t_s: np.ndarray, s: np.ndarray) -> float:
    """Highest mean of ``s`` over any window of 1 s (samples evenly spaced)."""
    if s.size < 2:
        return float(s.max()) if s.size else 0.0
    dt = float(np.median(np.diff(t_s)))
    n = max(1, round(1.0 / dt))
    if s.size < n:
        return float(s.mean())
    c = np.concatenate([[0.0], np.cumsum(s)])
    return float(np.max((c[n:] - c[:-n]) / n))


def bench_kpis(problem: BenchProblem, *, t_s: np.ndarray, s_va: np.ndarray,
               relays: Mapping[str, np.ndarray], relays_t_s: np.ndarray,
               levels: Mapping[str, np.ndarray], levels_t_s: np.ndarray, cycles: float,
               limit_va: float | None = None, dwell_tol_s: float = 0.005) -> dict[str, object]:
    """The KPI dictionary of a run (signals as recorded; times in seconds)."""
    t_s, s_va = np.asarray(t_s, float), np.asarray(s_va, float)
    dt = np.diff(t_s, append=t_s[-1] + (t_s[-1] - t_s[-2] if t_s.size > 1 else 0.0))
    energy = float(np.sum(s_va * dt))
    names = problem.peripherals
    on = {n: np.asarray(relays[n]).astype(bool) for n in names}
    rdt = np.diff(relays_t_s, append=relays_t_s[-1] + (relays_t_s[-1] - relays_t_s[-2]
                                                       if relays_t_s.size > 1 else 0.0))
    both = np.logical_and.reduce([on[n] for n in names]) if len(names) > 1 else \
        np.zeros_like(rdt, dtype=bool)
    kpis: dict[str, object] = {
        "J1_VA": round(energy, 1),
        "J2_VA": round(float(s_va.max()), 2),
        "SEC_VA": round(energy / cycles, 1) if cycles else None,
        "peak_VA": round(one_second_peak(t_s, s_va), 2),
        "energy_VAs": round(energy, 1),
        "overlap_s": round(float(np.sum(rdt[both])), 2),
        "dwell_violations": sum(dwell_violations(relays_t_s, on[n], problem.dwell_s[n],
                                                 dwell_tol_s) for n in names),
        "level_violations": sum(excursions(levels[r.name], r.q_min, r.q_max)
                                for r in problem.resources),
        "switches": {n: int(transitions(on[n]).size + (1 if on[n].size and on[n][0] else 0))
                     for n in names},
    }
    hours = max(float(relays_t_s[-1] - relays_t_s[0]), 1e-9) / 3600.0 if relays_t_s.size else 0.0
    kpis["starts_per_hour"] = {n: round(switch_ons(on[n]) / hours, 1) if hours else 0.0
                               for n in names}
    if limit_va is not None:
        kpis["over_limit_s"] = round(float(np.sum(dt[s_va > limit_va])), 2)
    return kpis


def timing_summary(samples_ms: Sequence[float]) -> dict[str, float]:
    """{median, p99, max} of decision times in ms (zeros when there are none)."""
    x = np.asarray(samples_ms, float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"median": 0.0, "p99": 0.0, "max": 0.0}
    return {"median": round(float(np.median(x)), 3),
            "p99": round(float(np.percentile(x, 99)), 3),
            "max": round(float(x.max()), 3)}
