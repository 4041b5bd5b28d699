"""What a servo run decided before it opened anything (:class:`ServoPlan`, frozen), and what it
opened and built since (:class:`ServoState`): the two things the steps of
:class:`~hil.servo.run.ServoExperiment` read.

:func:`plan_servo` checks and decides everything that needs no I/O: the settings resolved from
the options and the configuration, the axes (named, or the one of ``[master]``), each axis'
scenario, the controller spec loaded and its period checked, the limits split, each bus
planned (a real bus whose plan does not fit is refused), the session's path and metadata.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from hil.controllers.base import cycle_periods_of
from hil.controllers.servo.references import (
    CircleAxis,
    PlacedReference,
    Scenario,
    parse_circle,
    parse_scenario,
)
from hil.core.clock import RealtimeClock, SimClock
from hil.core.plugins import controller_factory, controller_short_name
from hil.core.registry import scheme_of
from hil.core.run import RunPlan, default_session_path
from hil.core.settings import settings_json
from hil.core.verdict import SignalWatch, split_limits
from hil.drivers.can_bus_time import BusPlan
from hil.drivers.canopen import CanDriveMaster
from hil.errors import UsageError
from hil.servo.axes import (
    AxesTick,
    BusAxes,
    bus_lock_key,
    carries_can,
    parse_axes,
    plan_buses,
)
from hil.servo.config import EMULATED, AxisSpec, DriveConfig, stricter_safety
from hil.servo.drives import RunDrives
from hil.servo.kpis import AxesKpis, ServoKpis
from hil.servo.options import ServoRunOptions
from hil.servo.rig import lone_axis
from hil.servo.settings import (
    ServoSettings,
    check_controller_output,
    check_controller_period,
    resolve_servo,
)
from hil.servo.task import ServoTask

# per-tick signals a --limit may name (magnitudes, except the position)
SIGNALS = ("abs_error_deg", "abs_command_mA", "abs_velocity_deg_s", "position_deg")


@dataclass(frozen=True, kw_only=True)
class ServoPlan(RunPlan):
    """A servo run, decided: the pipeline's :class:`~hil.core.run.RunPlan` and the servo's
    own. ``lone``: the run names no axis (its one axis records ``/drive/...``, flat KPIs)."""

    settings: ServoSettings
    axes: tuple[AxisSpec, ...]
    lone: bool
    scenarios: tuple[Scenario, ...]
    radius: float | None              # a circle's (None: no path)
    params: Mapping[str, Any]
    factory: Callable[..., Any]       # the controller's, loaded and checked
    buses: tuple[BusAxes, ...]

    @property
    def drive(self) -> DriveConfig:
        return self.settings.drive

    @property
    def bus_of(self) -> dict[str, str]:
        """Each axis' bus URL by its name."""
        return axis_buses(self.buses)

    def umax_for(self, master: CanDriveMaster) -> float:
        """The current bound of the controller of ``master``'s axis [mA]: the run's, or the
        drive's limit where it is lower."""
        return min(self.settings.umax_ma, master.current_limit_ma)

    def axis_params(self, name: str) -> dict[str, Any]:
        """Axis ``name``'s parameters: the common ones, and ``NAME.KEY`` laid over them (a run
        that names no axis: all of them, as given)."""
        if self.lone:
            return dict(self.params)
        common = {k: v for k, v in self.params.items() if "." not in k}
        return common | {k.partition(".")[2]: v for k, v in self.params.items()
                         if k.startswith(f"{name}.")}

    def period_note(self, bus: BusPlan) -> str:
        """Which longer period the run's controller runs at (when its periods can be listed):
        the shortest the bus plan fits."""
        periods = cycle_periods_of(self.factory)
        if not isinstance(periods, (range, tuple, list, set, frozenset)):
            return ""
        longer = [p for p in sorted(periods) if p >= bus.min_period_us]
        label = self.settings.options.label
        return (f"; controller {label!r} runs at {longer[0]} us" if longer else
                f"; controller {label!r} runs at no period that long")


@dataclass
class ServoState:
    """What a servo run opened and built, step by step: the drives (bus by bus), each axis'
    master, reference, controller and task (in the run's order) and, for named axes, the
    loop's one task that ticks them (``axes_tick``)."""

    drives: RunDrives = field(default_factory=RunDrives)
    masters: list[CanDriveMaster] = field(default_factory=list)
    references: list[PlacedReference] = field(default_factory=list)
    controllers: list[Any] = field(default_factory=list)
    tasks: list[ServoTask] = field(default_factory=list)
    axes_tick: AxesTick | None = None


def plan_servo(options: ServoRunOptions) -> ServoPlan:
    """The plan of a servo run with ``options`` (see the module); a HilError on bad input."""
    settings = resolve_servo(options)
    drive = settings.drive
    named = parse_axes(options.axes) if options.axes else drive.axes
    axes = named or (lone_axis(drive),)
    scenarios, radius = _scenarios(options, len(axes))
    params = {**drive.run.params, **options.params}
    if named:
        _check_axis_params(options, axes)
    # checked before anything is opened: a spec that cannot load leaves no file behind
    factory, _ = controller_factory(options.controller, scenarios[0].reference, params,
                                    method="step", application="servo")
    check_controller_period(factory, options.label, drive)
    check_controller_output(factory, options.label, drive)
    kpi_limits, signal_limits = split_limits(
        [*drive.run.limits, *options.limits], SIGNALS,
        (AxesKpis if named else ServoKpis).limit_names())
    buses = tuple(plan_buses(axes, settings.drive_url, drive))
    out = options.out or default_session_path("servo", controller_short_name(options.label))
    run_info = options.record() | {
        "controller": options.label, "params": params,
        "limits": [str(lim) for lim in (*kpi_limits, *signal_limits)]}
    if named:
        bus_of = axis_buses(buses)
        run_info["axes"] = [{"name": a.name, "node": a.node, "bus": bus_of[a.name],
                             "eds": a.master(drive.master).eds,
                             "safety": vars(stricter_safety(drive.safety, a.safety))}
                            for a in axes]
    plan = ServoPlan(
        kind="servo", session_path=out,
        label=f"{options.label} on {len(axes)} axes" if named else options.label,
        clock=RealtimeClock() if options.realtime else SimClock(),
        base_period_s=drive.master.cycle_period_s, duration_s=options.duration_s,
        kpi_limits=tuple(kpi_limits), watch=SignalWatch(signal_limits),
        config={"servo": run_info, "drive": drive.data,
                "settings": settings_json(settings.settings())},
        config_text=drive.text, config_name="drive.toml", recording=options.recording,
        devices=tuple(("drive bus", bus_lock_key(bus.url)) for bus in buses
                      if scheme_of(bus.url) not in (EMULATED, "virtual")),
        quiet=options.quiet,
        settings=settings, axes=axes, lone=not named, scenarios=tuple(scenarios),
        radius=radius, params=params, factory=factory, buses=buses)
    for bus in buses:
        # the in-process bus has no bitrate
        if not bus.plan.fits and bus.url != EMULATED and carries_can(bus.url):
            raise UsageError(f"the bus plan does not fit ({bus.url}): "
                             f"{bus.plan.problem(plan.period_note(bus.plan))} (see "
                             f"'hil drive plan --axes {len(bus.axes)}')")
    return plan


def axis_buses(buses: tuple[BusAxes, ...]) -> dict[str, str]:
    """Each axis' bus URL by the axis' name."""
    return {axis.name: bus.url for bus in buses for axis in bus.axes}


def _scenarios(options: ServoRunOptions, axes: int) -> tuple[list[Scenario], float | None]:
    """Every axis' scenario (a circle's axis each, or ``--reference`` for all) and the
    circle's radius (None: no path)."""
    circle = parse_circle(options.reference)
    if circle is None:
        return [parse_scenario(options.reference)] * axes, None
    if axes != 2:
        raise UsageError(f"--reference {options.reference}: a circle needs two axes, "
                         f"{'--axes names' if options.axes else 'the run has'} {axes}")
    return [Scenario(CircleAxis(circle[0], circle[1], i)) for i in range(2)], circle[0]


def _check_axis_params(options: ServoRunOptions, axes: tuple[AxisSpec, ...]) -> None:
    names = [axis.name for axis in axes]
    for key in options.params:
        axis, dot, _ = key.partition(".")
        if dot and axis not in names:
            raise UsageError(f"--param {key}: no axis {axis!r} (the axes: {', '.join(names)}); "
                             "NAME.KEY=VALUE sets KEY for axis NAME")
