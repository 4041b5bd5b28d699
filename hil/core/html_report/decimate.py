"""Min/max decimation: a long signal drawn with few points that keeps every peak."""

from __future__ import annotations

import numpy as np


def minmax_decimate(t: np.ndarray, y: np.ndarray, max_points: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """At most ``max_points`` samples of ``(t, y)``: the signal cut into at most
    ``max_points // 2`` runs of equal length, each kept as its smallest and its largest sample
    in time order, so every peak and dip is drawn. A signal that fits is returned as it is; a
    NaN sample is chosen only in a run of NaNs."""
    n = y.size
    if n <= max_points:
        return t, y
    width = -(-n // max(1, max_points // 2))   # samples per run, rounded up
    buckets = -(-n // width)                    # the last run may be shorter
    values = np.full(buckets * width, np.nan)
    values[:n] = y
    rows = values.reshape(buckets, width)
    low = np.argmin(np.where(np.isnan(rows), np.inf, rows), axis=1)
    high = np.argmax(np.where(np.isnan(rows), -np.inf, rows), axis=1)
    starts = np.arange(buckets) * width
    keep = np.unique(np.concatenate([starts + low, starts + high]))
    return t[keep], y[keep]
