"""Two recordings of one signal on one time base (pure numpy).

Lockstep sessions tick on the same virtual clock: their samples are matched tick for tick
(the times both hold). Real-time sessions do not share ticks: the candidate is interpolated
linearly onto the baseline's ticks within the candidate's span.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Series:
    """One signal of one session: ``t_ns`` from the session's start, ``values`` as floats."""

    t_ns: np.ndarray
    values: np.ndarray


@dataclass(frozen=True)
class Aligned:
    """Baseline and candidate on the baseline's ticks: ``t_s``, ``baseline``, ``candidate``;
    ``index``: where those ticks are in the baseline's whole series."""

    t_s: np.ndarray
    baseline: np.ndarray
    candidate: np.ndarray
    index: np.ndarray


def tick_for_tick(base: Series, cand: Series) -> Aligned:
    """The ticks both sessions hold, matched by their exact time."""
    common, ib, ic = np.intersect1d(base.t_ns, cand.t_ns, return_indices=True)
    return Aligned(common / 1e9, base.values[ib], cand.values[ic], ib)


def interpolated(base: Series, cand: Series) -> Aligned:
    """The candidate interpolated onto the baseline's ticks that lie within its own span."""
    if cand.t_ns.size == 0:
        return Aligned(np.empty(0), np.empty(0), np.empty(0), np.empty(0, dtype=np.intp))
    index = np.flatnonzero((base.t_ns >= cand.t_ns[0]) & (base.t_ns <= cand.t_ns[-1]))
    t = base.t_ns[index]
    return Aligned(t / 1e9, base.values[index], np.interp(t, cand.t_ns, cand.values), index)


def window_extremes(values: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """The smallest and largest value within ``half`` samples either side of each sample."""
    low, high = values.copy(), values.copy()
    n = values.size
    for shift in range(1, min(half, n - 1) + 1 if n else 0):
        low[shift:] = np.fmin(low[shift:], values[:-shift])
        low[:-shift] = np.fmin(low[:-shift], values[shift:])
        high[shift:] = np.fmax(high[shift:], values[:-shift])
        high[:-shift] = np.fmax(high[:-shift], values[shift:])
    return low, high
