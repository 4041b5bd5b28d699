"""A difference held against its tolerance: one KPI, or one aligned signal (its worst tick)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hil.compare.alignment import Aligned, Series, window_extremes
from hil.compare.tolerances import MAX, MIN, Tolerance


@dataclass(frozen=True)
class Verdict:
    """``difference`` the largest excursion outside the tolerance (failed) or the largest
    difference inside it (passed); ``index`` the tick of it (signals)."""

    passed: bool
    difference: float
    index: int = 0


def judge_kpi(tolerance: Tolerance, baseline: float, candidate: float) -> Verdict:
    """candidate - baseline within the tolerance, on the sides it bounds (NaN equals only
    NaN)."""
    if math.isnan(baseline) or math.isnan(candidate):
        same = math.isnan(baseline) and math.isnan(candidate)
        return Verdict(same, 0.0 if same else math.nan)
    difference = candidate - baseline
    return Verdict(tolerance.holds(difference, tolerance.allowed(baseline)), difference)


def judge_signal(tolerance: Tolerance, aligned: Aligned, baseline: Series) -> Verdict:
    """Every aligned tick within the tolerance; a tube lets the candidate lead or lag the
    baseline by ``lag_s``: the band is around the baseline's extremes within that window
    (of its whole series: ``baseline``); a one-sided tolerance bounds one side of it."""
    base, cand = aligned.baseline, aligned.candidate
    low, high = base, base
    if tolerance.kind == "tube" and tolerance.lag_s > 0 and baseline.t_ns.size > 1:
        step = float(np.median(np.diff(baseline.t_ns))) / 1e9
        half = math.ceil(tolerance.lag_s / step - 1e-9) if step > 0 else 0
        low, high = (extreme[aligned.index] for extreme in
                     window_extremes(baseline.values, half))
    if tolerance.kind == "rel":
        allowed = tolerance.value * np.abs(base)
    else:
        allowed = np.full(base.shape, tolerance.allowed(0.0))
    with np.errstate(invalid="ignore"):
        above, below = cand - (high + allowed), (low - allowed) - cand
    if tolerance.side == MAX:
        below = np.where(np.isnan(below), np.nan, -np.inf)
    elif tolerance.side == MIN:
        above = np.where(np.isnan(above), np.nan, -np.inf)
    outside = np.fmax(np.fmax(above, below), 0.0)
    both_nan = np.isnan(base) & np.isnan(cand)
    outside = np.where(both_nan, 0.0, np.where(np.isnan(outside), np.inf, outside))
    if outside.size and outside.max() > 0:
        index = int(np.argmax(outside))
        return Verdict(False, float(outside[index]), index)
    inside = np.where(both_nan, 0.0, np.abs(cand - base))
    index = int(np.argmax(inside)) if inside.size else 0
    return Verdict(True, float(inside[index]) if inside.size else 0.0, index)
