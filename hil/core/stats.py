"""Constant-memory timing statistics: exact count/max, percentiles to 1 us from a histogram."""

from __future__ import annotations

import numpy as np

_MAX_BIN_US = 100_000  # 100 ms; slower samples land in the last bin (their exact max is kept)


class TimingHistogram:
    """Collects durations in microseconds; p50/p99 resolved to 1 us, max exact."""

    def __init__(self) -> None:
        self._bins = np.zeros(_MAX_BIN_US + 1, dtype=np.int64)
        self.count = 0
        self.max_us = 0.0
        self._sum_us = 0.0

    def add_many(self, samples_us: list[float] | np.ndarray) -> None:
        if len(samples_us) == 0:
            return
        values = np.asarray(samples_us, dtype=np.float64)
        idx = np.clip(values, 0, _MAX_BIN_US).astype(np.int64)
        counts = np.bincount(idx)
        self._bins[: counts.size] += counts
        self.count += values.size
        self.max_us = max(self.max_us, float(values.max()))
        self._sum_us += float(values.sum())

    def percentile(self, q: float) -> float:
        """The q-th percentile (0-100) in us, 0.0 when empty."""
        if self.count == 0:
            return 0.0
        rank = int(np.ceil(q / 100.0 * self.count))
        return float(np.searchsorted(np.cumsum(self._bins), max(rank, 1)))

    def mean(self) -> float:
        return self._sum_us / self.count if self.count else 0.0

    def summary(self) -> dict[str, float]:
        return {
            "p50": self.percentile(50),
            "p99": self.percentile(99),
            "max": round(self.max_us, 3),
            "mean": round(self.mean(), 3),
        }


def percentile_summary(samples_us: np.ndarray) -> dict[str, float]:
    """Median, p99 and max of an array of durations (us); zeros when empty."""
    if samples_us.size == 0:
        return {"p50": 0.0, "p99": 0.0, "max": 0.0, "mean": 0.0}
    p50, p99 = np.percentile(samples_us, [50, 99])
    return {
        "p50": round(float(p50), 3),
        "p99": round(float(p99), 3),
        "max": round(float(samples_us.max()), 3),
        "mean": round(float(samples_us.mean()), 3),
    }
