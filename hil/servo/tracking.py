"""What a servo run measures: the tracking KPIs,
accumulated tick by tick in constant memory.

KPIs are taken over the ticks from ``settle_s`` on: the error is the multi-turn position
(as the master counts it) minus the reference placed where the axis started
(:class:`~hil.controllers.servo.references.PlacedReference`), turns included, so a runaway's whole
error shows; ``max_error_pct`` is relative to the sine's amplitude or the trapezoid's stroke
(None for a hold); the peak currents are None where the drive chose the current and does not
measure it (no 0x6077); ``step_us`` is the controller's compute time (Kalman + MPC, or PID) per
tick.
"""

from __future__ import annotations

import math

from hil.controllers.servo.references import Scenario, Sine, Trapezoid
from hil.core.stats import TimingHistogram
from hil.servo.kpis import TrackingKpis


def reference_amplitude(scenario: Scenario) -> float | None:
    """What ``max_error_pct`` is relative to: a sine's amplitude, a trapezoid's stroke."""
    ref = scenario.reference
    if isinstance(ref, Sine):
        return abs(ref.amplitude) or None
    if isinstance(ref, Trapezoid):
        return ref.stroke
    return None


class TrackingStats:
    """The run's KPIs, accumulated tick by tick in constant memory: error and current over the
    ticks from ``settle_s`` on (exact running sums and maxima), controller compute time over
    all ticks (a log-bucket histogram: percentiles within 1 %, max exact; each tick's time
    binned as it comes, the same small work every tick: binned 128 at a time, one numpy call
    cost every 128th tick some 40 us)."""

    def __init__(self, settle_s: float) -> None:
        self.settle_s = settle_s - 1e-12
        self.ticks = 0
        self.counted = 0
        self.max_error = 0.0
        self.sum_error = 0.0
        self.sum_squares = 0.0
        self.peak_current = 0.0    # the current the drive was sent (after the clamp)
        self.peak_requested = 0.0  # the controller's request
        self.measured = False      # a current was known (a drive without 0x6077 reports NaN)
        self.compute_us = TimingHistogram()

    def add(self, t_s: float, error_deg: float, command_ma: float, compute_us: float,
            requested_ma: float | None = None) -> None:
        """One tick: ``command_ma`` is the current the drive was sent, ``requested_ma`` the
        controller's request (the same when not given)."""
        self.ticks += 1
        self.compute_us.add(compute_us)
        if not t_s >= self.settle_s:  # before settle_s (as a NaN time would be)
            return
        e = abs(error_deg)
        self.counted += 1
        self.sum_error += e
        self.sum_squares += e * e
        if e > self.max_error:
            self.max_error = e
        current = abs(command_ma)
        if current > self.peak_current:
            self.peak_current = current
        if current == current:  # NaN: not measured
            self.measured = True
        requested = current if requested_ma is None else abs(requested_ma)
        if requested > self.peak_requested:
            self.peak_requested = requested

    def kpis(self, amplitude: float | None) -> TrackingKpis:
        """The tracking KPIs so far (``amplitude``: the reference's, for the error in %)."""
        step = self.compute_us.summary()
        kpis = TrackingKpis(step_us={"median": step["p50"], "p99": step["p99"], "max": step["max"]})
        if self.counted:
            kpis.max_error_deg = self.max_error
            kpis.max_error_pct = 100.0 * self.max_error / amplitude if amplitude else None
            kpis.rms_error_deg = math.sqrt(self.sum_squares / self.counted)
            kpis.cumulative_error_deg = self.sum_error
            if self.measured:
                kpis.peak_current_ma = self.peak_current
                kpis.peak_requested_ma = self.peak_requested
        return kpis
