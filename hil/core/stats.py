"""Constant-memory statistics of durations: a log-bucket (HDR-style) histogram.

:class:`TimingHistogram` keeps a fixed array of ``BUCKETS`` counters, whatever the number of
samples: count, sum, min and max are exact; a percentile is within ``RELATIVE_ACCURACY``
(1 %) of the exact one for values from ``LOWEST`` (0.01) to ``HIGHEST`` (1e9, in the caller's
unit: 1e9 us is about 17 min); below ``LOWEST`` the error is at most ``LOWEST``.

:meth:`TimingHistogram.add` bins its one sample at once, in constant time: a loop that adds a
sample every tick does the same work at every tick (no batch binned every N samples, which
would cost one tick the work of N). A sample's bucket is found by bisecting the buckets' lower
bounds (:data:`BOUNDS`), one C call, and :meth:`TimingHistogram.add_many` searches the same
bounds: a value lands in the same bucket either way.
"""

from __future__ import annotations

import math
from bisect import bisect_right

import numpy as np

RELATIVE_ACCURACY = 0.01
LOWEST = 1e-2
HIGHEST = 1e9
# bucket i >= 1 holds [LOWEST g^(i-1), LOWEST g^i); its representative 2 g L / (1 + g) is
# within (g - 1) / (g + 1) of every value in it: g = (1 + a) / (1 - a) gives exactly a
_GROWTH = (1 + RELATIVE_ACCURACY) / (1 - RELATIVE_ACCURACY)
_LOG_GROWTH = math.log(_GROWTH)
BUCKETS = math.ceil(math.log(HIGHEST / LOWEST) / _LOG_GROWTH) + 2  # + below LOWEST, + above
#: bucket i >= 1 holds the values from BOUNDS[i - 1] (LOWEST g^(i-1)) up to the next bound: a
#: value's bucket is how many bounds it has reached
_BOUNDS_ARRAY = LOWEST * _GROWTH ** np.arange(BUCKETS - 1)
BOUNDS: list[float] = _BOUNDS_ARRAY.tolist()
_REPRESENTATIVE = np.concatenate([[0.0], _BOUNDS_ARRAY * 2 * _GROWTH / (1 + _GROWTH)])


class TimingHistogram:
    """Durations (any non-negative unit, us by convention): exact count, sum, min, max;
    percentiles within ``RELATIVE_ACCURACY`` from ``BUCKETS`` fixed counters."""

    __slots__ = ("_bins", "_singles", "_sum", "count", "max_us", "min_us")

    def __init__(self) -> None:
        self._bins = np.zeros(BUCKETS, dtype=np.int64)  # the batches' counts (add_many)
        self._singles = [0] * BUCKETS  # the single samples' counts (add): a list is cheaper
        self._sum = 0.0
        self.count = 0
        self.max_us = 0.0
        self.min_us = math.inf

    def add(self, value: float) -> None:
        """One sample (negative counts as 0, NaN and infinities are ignored), binned now."""
        if not math.isfinite(value):
            return
        v = value if value > 0.0 else 0.0
        self._singles[bisect_right(BOUNDS, v)] += 1
        self.count += 1
        self._sum += v
        if v > self.max_us:
            self.max_us = v
        if v < self.min_us:
            self.min_us = v

    def add_many(self, samples_us: list[float] | np.ndarray) -> None:
        """A batch of samples (negative values count as 0, NaN and infinities are ignored)."""
        values = np.asarray(samples_us, dtype=np.float64)
        values = np.maximum(values[np.isfinite(values)], 0.0)
        if values.size == 0:
            return
        self._bins += np.bincount(bucket_of(values), minlength=BUCKETS)
        self.count += values.size
        self._sum += float(values.sum())
        self.max_us = max(self.max_us, float(values.max()))
        self.min_us = min(self.min_us, float(values.min()))

    def percentile(self, q: float) -> float:
        """The q-th percentile (0-100), linearly interpolated between the two nearest ranks
        as ``numpy.percentile`` does; 0.0 when empty."""
        if self.count == 0:
            return 0.0
        h = (self.count - 1) * min(max(q, 0.0), 100.0) / 100.0
        below = math.floor(h)
        lower, upper = self._value_at_rank(below), self._value_at_rank(min(below + 1,
                                                                            self.count - 1))
        return lower + (h - below) * (upper - lower)

    def _value_at_rank(self, rank: int) -> float:
        """The estimate of the ``rank``-th smallest sample (0-based), within [min, max]."""
        if rank == 0:
            return self.min_us
        if rank == self.count - 1:
            return self.max_us
        counts = self._bins + np.asarray(self._singles, dtype=np.int64)
        bucket = int(np.searchsorted(np.cumsum(counts), rank, side="right"))
        return min(max(float(_REPRESENTATIVE[bucket]), self.min_us), self.max_us)

    def mean(self) -> float:
        return self._sum / self.count if self.count else 0.0

    def summary(self) -> dict[str, float]:
        """p50, p99 (within the stated accuracy), exact max and mean, rounded to 3 decimals."""
        return {
            "p50": round(self.percentile(50), 3),
            "p99": round(self.percentile(99), 3),
            "max": round(self.max_us, 3),
            "mean": round(self.mean(), 3),
        }


def bucket_of(values: np.ndarray) -> np.ndarray:
    """The bucket index of each value >= 0 (0: below ``LOWEST``; the last: from the last
    bound, ``HIGHEST`` or just above, on), as :meth:`TimingHistogram.add` bins one."""
    return np.searchsorted(_BOUNDS_ARRAY, values, side="right")


def percentile_summary(samples_us: np.ndarray) -> dict[str, float]:
    """Median, p99 and max of an array of durations (us), exact; zeros when empty."""
    if samples_us.size == 0:
        return {"p50": 0.0, "p99": 0.0, "max": 0.0, "mean": 0.0}
    p50, p99 = np.percentile(samples_us, [50, 99])
    return {
        "p50": round(float(p50), 3),
        "p99": round(float(p99), 3),
        "max": round(float(samples_us.max()), 3),
        "mean": round(float(samples_us.mean()), 3),
    }
