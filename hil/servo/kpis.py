"""The servo run's KPI documents (``hil servo run --json``), as :class:`~hil.core.kpis.Kpis`
dataclasses: the names a ``--limit`` may use, the JSON keys and the JUnit properties all come
from their fields.

* :class:`TrackingKpis` - one axis' tracking after ``settle_s`` (:mod:`hil.servo.tracking`);
* :class:`ServoKpis` - a run that names no axis: the flat document docs/guides documents;
* :class:`AxisKpis`, :class:`ContourKpis`, :class:`AxesKpis` - a run on named axes: each axis'
  KPIs under ``axes.NAME``, a circle's under ``contour``.
"""

from __future__ import annotations

from dataclasses import dataclass

from hil.core.kpis import Kpis, kpi


@dataclass
class TrackingKpis(Kpis):
    """One axis' tracking error after ``settle_s`` [deg], its controller's step time [us], and
    its peak currents [mA]: sent to the drive (after the clamp) and requested."""

    max_error_deg: float | None = kpi()
    max_error_pct: float | None = kpi()
    rms_error_deg: float | None = kpi()
    cumulative_error_deg: float | None = kpi()
    step_us: dict[str, float] | None = kpi()
    peak_current_ma: float | None = kpi(key="peak_current_mA")
    peak_requested_ma: float | None = kpi(key="peak_requested_mA")


@dataclass
class ServoKpis(Kpis):
    """A run on one axis, the documented keys first, then context."""

    controller: str = kpi("", limit=False)
    max_error_deg: float | None = kpi()
    max_error_pct: float | None = kpi()
    rms_error_deg: float | None = kpi()
    cumulative_error_deg: float | None = kpi()
    step_us: dict[str, float] | None = kpi()
    deadline_misses: int = kpi(0)
    ticks: int = kpi(0)
    cycle_period_us: int = kpi(0, limit=False)
    mcap: str = kpi("", limit=False)
    reference: str = kpi("", limit=False)
    drive: str = kpi("", limit=False)
    clock: str = kpi("", limit=False)
    umax_ma: float | None = kpi(key="umax_mA", limit=False)
    current_limit_ma: float | None = kpi(key="current_limit_mA", limit=False)  # the chain's
    settle_s: float = kpi(0.0, limit=False)
    peak_current_ma: float | None = kpi(key="peak_current_mA")      # sent, after the clamp
    peak_requested_ma: float | None = kpi(key="peak_requested_mA")  # the controller's request
    stale_feedback: int = kpi(0)
    clamped_commands: int = kpi(0)
    wall_s: float = kpi(0.0)
    realtime_factor: float | None = kpi()
    stop_reason: str | None = kpi(limit=False)
    # what the controller sent a drive that closes its own loop (position: CSP; velocity: CSV,
    # PV); absent, a current (CST). The peak currents are then the drive's (torque actual)
    set_point: str | None = kpi(limit=False, optional=True)
    ert: str | None = kpi(limit=False, optional=True)   # an MPC's horizons
    ht: int | None = kpi(limit=False, optional=True)
    hu: int | None = kpi(limit=False, optional=True)
    hp: int | None = kpi(limit=False, optional=True)
    solver_paths: dict[str, int] | None = kpi(optional=True)
    empc_fallbacks: int | None = kpi(optional=True)
    faults: dict[str, int] | None = kpi()
    disturbed: bool = kpi(False, limit=False)


@dataclass
class AxisKpis(TrackingKpis):
    """One named axis: its tracking, its drive and what its master counted."""

    node: int = kpi(0, limit=False)
    bus: str = kpi("", limit=False)
    stale_feedback: int = kpi(0)
    clamped_commands: int = kpi(0)
    current_limit_ma: float | None = kpi(key="current_limit_mA", limit=False)
    late_frames: int = kpi(0)
    emcy: int = kpi(0)


@dataclass
class ContourKpis(Kpis):
    """A circle's contour error after ``settle_s`` [deg] (None before a counted tick)."""

    radius_deg: float | None = kpi(limit=False)
    max_contour_error_deg: float | None = kpi()
    rms_contour_error_deg: float | None = kpi()


@dataclass
class AxesKpis(Kpis):
    """A run on named axes: each axis' KPIs under ``axes``, then the run's."""

    controller: str = kpi("", limit=False)
    axes: dict[str, AxisKpis] | None = kpi()
    ticks: int = kpi(0)
    cycle_period_us: int = kpi(0, limit=False)
    mcap: str = kpi("", limit=False)
    reference: str = kpi("", limit=False)
    drive: str = kpi("", limit=False)
    buses: list[str] | None = kpi(limit=False)
    clock: str = kpi("", limit=False)
    umax_ma: float | None = kpi(key="umax_mA", limit=False)
    settle_s: float = kpi(0.0, limit=False)
    sync_cycles: int = kpi(0)
    wall_s: float = kpi(0.0)
    realtime_factor: float | None = kpi()
    stop_reason: str | None = kpi(limit=False)
    contour: ContourKpis | None = kpi(optional=True)
    faults: dict[str, int] | None = kpi()
    disturbed: bool = kpi(False, limit=False)


def no_tracking() -> TrackingKpis:
    """The tracking of an axis that never ticked."""
    return TrackingKpis(step_us={"median": 0.0, "p99": 0.0, "max": 0.0})
