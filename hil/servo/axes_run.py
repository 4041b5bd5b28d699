"""``hil servo run --axes x=1,y=2``: several axes, one SYNC per tick on each bus.

Each axis is one drive (its node id) with its own master on its bus's
:class:`~hil.drivers.canopen.axes.AxisBus`, its own controller (the run's, built once per axis
with that axis' reference) and its own servo task (topics ``/axis/NAME/command``,
``/axis/NAME/feedback``, ``/axis/NAME/prediction``). The axes are on the run's bus (``--drive``
or ``[bus]``) unless one names another (``--axes x=1,y=2@URL``, ``[[axis]] bus = URL``): every
axis of a bus shares that bus's SYNC, and every bus has its cycle and SYNC in every tick. The
tick's phases run axis by axis, and a bus task comes last: its write ends every bus's cycle
(each axis' RPDO, then one SYNC), its record logs the contour error of a path
(``/path/contour``). A stop of any kind (a safety limit, a fault, Ctrl-C) stops every axis of
every bus in the same cycles (:meth:`~hil.drivers.canopen.axes.AxisGroup.stop_together`).

Each bus is planned before anything opens (:func:`hil.drivers.canopen.master.plan_axes`, the figure
``hil drive plan`` prints: the worst-case bus time of a cycle against the period): a real bus
whose plan does not fit is refused with the ways out; the emulated one, which has no bit rate,
runs with a warning on the terminal and a ``bus.plan`` event.

References: ``--reference`` as for one axis (every axis the same), or the path
``circle:radius=R,feed=F`` for two axes (a circular test, ISO 230-4: R in degrees of each
axis, F in degrees per second along the path). Parameters: ``--param KEY=V`` for every axis,
``--param NAME.KEY=V`` for axis NAME (a gain mismatch between axes, say).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from can.interfaces import VALID_INTERFACES

from hil.controllers.base import UNWRAPPED, cycle_periods_of, position_input_of
from hil.controllers.servo.references import (
    CircleAxis,
    PlacedReference,
    Scenario,
    contour_error,
    parse_circle,
)
from hil.core.clock import Clock
from hil.core.loop import Task
from hil.core.notice import warn
from hil.core.plugins import build_controller
from hil.core.registry import scheme_of
from hil.core.run import EventBuffer, RunPlan, RunResult, controller_budget, run_experiment
from hil.core.session import Session
from hil.drivers.can_bus_time import BusPlan
from hil.drivers.canopen import CanDriveMaster, CanLink, open_can_bus, parse_can_url
from hil.drivers.canopen.axes import AxisBus, AxisGroup
from hil.drivers.canopen.master import plan_axes
from hil.emulators.drive.runners import LockstepDrive
from hil.errors import ControllerError, HilError, SafetyStopError, UsageError
from hil.servo.config import AXIS_NAME, EMULATED, AxisSpec, DriveConfig, check_axes
from hil.servo.rig import share_lockstep_time
from hil.servo.run import (
    STEP_BUDGET_S,
    ServoExperiment,
    ServoRunOptions,
    make_controller,
    realtime_factor,
    run_servo,
)
from hil.servo.safety import SafetyMonitor
from hil.servo.settings import bus_bitrate, resolve_servo
from hil.servo.task import ServoTask
from hil.servo.tracking import reference_amplitude

CONTOUR_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.Contour",
    "description": "A path's contour error: distance of the axes' measured point (in the "
                   "path's frame: each position less its reference's offset) from the path "
                   "(> 0 outside a circle).",
    "properties": {
        "t_s": {"type": "number"},
        "x_deg": {"type": "number"},
        "y_deg": {"type": "number"},
        "contour_error_deg": {"type": "number", "x-cdr": "float32"},
    },
}


def parse_axes(text: str) -> tuple[AxisSpec, ...]:
    """``x=1,y=2@URL`` -> the axes, in order (an axis without ``@URL`` on the run's bus); a
    clear error for anything else."""
    axes = []
    for item in filter(None, (part.strip() for part in text.split(","))):
        axis, at, bus = item.partition("@")
        name, eq, node = axis.partition("=")
        if not eq or not AXIS_NAME.fullmatch(name) or not node.isdigit() or \
                not 1 <= int(node) <= 127 or (at and not bus.strip()):
            raise UsageError(f"--axes {text!r}: {item!r} is not NAME=NODE[@URL] (a lower-case "
                             "name, a CANopen node id 1..127, the URL of its bus when it is "
                             "not the run's), e.g. --axes x=1,y=2 or --axes "
                             "x=1,y=1@socketcand://127.0.0.1:29536")
        axes.append(AxisSpec(name, int(node), bus=bus.strip()))
    return check_axes(tuple(axes), f"--axes {text!r}")


def bus_key(url: str, channel: str) -> str:
    """One bus, one name: a python-can or socketcand URL as its parts say it (so two spellings
    of one bus are one bus); another scheme's URL as it is."""
    if scheme_of(url) not in VALID_INTERFACES:
        return url
    return parse_can_url(url, channel).url


@dataclass(frozen=True)
class BusAxes:
    """The axes on one bus, in the run's order, and the plan of that bus."""

    url: str
    axes: tuple[AxisSpec, ...]
    plan: BusPlan


def plan_buses(axes: tuple[AxisSpec, ...], run_url: str, drive: DriveConfig
               ) -> list[BusAxes]:
    """The buses of ``axes`` (an axis without a bus of its own on ``run_url``), in the order
    they first appear, each planned at its bit rate (:func:`plan_axes`)."""
    master = drive.master
    placed = tuple(replace(axis, bus=bus_key(axis.bus or run_url, master.channel))
                   for axis in axes)
    check_axes(placed, "the axes")
    buses = []
    for url in dict.fromkeys(axis.bus for axis in placed):
        on_bus = tuple(axis for axis in placed if axis.bus == url)
        plan = plan_axes(master, [axis.name for axis in on_bus], bus_bitrate(url, drive))
        buses.append(BusAxes(url, on_bus, plan))
    return buses


class SharedStep:
    """A multi-axis controller (``multi_axis = True``, built as ``Class(references,
    params)``, ``step(positions_deg: np.ndarray, t_s) -> currents_mA``) stepped once a tick
    with every axis' position (all read by then; ``position % 360``, or multi-turn as its
    ``position_input`` says), its currents kept for the axes' tasks."""

    def __init__(self, whole: Any, tasks: list[ServoTask], label: str) -> None:
        self.whole, self.tasks, self.label = whole, tasks, label
        self.unwrapped = position_input_of(whole, label) == UNWRAPPED
        self._t_s: float | None = None
        self._currents = np.zeros(0)

    def currents(self, t_s: float) -> np.ndarray:
        if self._t_s != t_s:  # the first axis of this tick steps the controller
            positions = np.array([task.feedback.position_deg for task in self.tasks])
            if not self.unwrapped:
                positions %= 360.0
            currents = np.asarray(self.whole.step(positions, t_s), dtype=float)
            if currents.shape != positions.shape:
                raise ControllerError(
                    f"controller {self.label!r}: a multi-axis step() must return one current "
                    f"per axis ({positions.size}), got shape {currents.shape}")
            self._t_s, self._currents = t_s, currents
        return self._currents


class AxisShare:
    """One axis' view of a :class:`SharedStep`: the servo contract for its task."""

    def __init__(self, shared: SharedStep, index: int) -> None:
        self.shared, self.index = shared, index

    def step(self, position_deg: float, t_s: float) -> float:
        return float(self.shared.currents(t_s)[self.index])


class AxisGroups:
    """The axis groups of a run, one per bus, started bus by bus, cycled in every tick and
    stopped together: quick stop on every axis of every bus in the same cycles until all
    stand, then disable voltage in one cycle too."""

    def __init__(self, groups: list[AxisGroup]) -> None:
        self.groups = groups
        self.masters = [master for group in groups for master in group.masters]

    def cycle_together(self) -> None:
        for group in self.groups:
            group.bus.cycle_together(True)

    def end_cycle(self) -> None:
        """Every bus's cycle: its axes' RPDOs, then its SYNC."""
        for group in self.groups:
            group.bus.end_cycle()

    def safe_state(self) -> None:
        """Every axis stopped in the same cycles (:meth:`AxisGroup.stop_together`); silent."""
        if all(group.bus.together for group in self.groups):
            AxisGroup.stop_together(self.groups)
        else:  # still setting up: one drive after the other
            for master in self.masters:
                master.safe_state()

    def close(self) -> None:
        """Stop together, then release every master (each bus with its last), each bus
        passing frames through again first: a master's last SDO writes (its drive's own
        limits back) are no cycle's, nothing would send them."""
        try:
            self.safe_state()
        finally:
            for group in self.groups:
                group.bus.cycle_together(False)
            for master in self.masters:
                master.disconnect()


class BusCycle(Task):
    """Last in the tick: the cycle on every bus (each axis' RPDO, one SYNC a bus), then the
    path's contour error."""

    def __init__(self, session: Session, buses: AxisGroups, tasks: list[ServoTask],
                 radius: float | None, settle_s: float) -> None:
        super().__init__("bus")
        self.buses, self.tasks, self.radius = buses, tasks, radius
        self.settle_s = settle_s
        self.topic = session.topic("/path/contour", CONTOUR_SCHEMA, high_rate=True) \
            if radius is not None else None
        self.max_error = 0.0
        self.sum_squares = 0.0
        self.counted = 0
        self.cycles = 0  # cycles put on the bus while ticking

    def write(self, t_ns: int) -> None:
        self.buses.end_cycle()
        self.cycles += 1

    def record(self, t_ns: int) -> None:
        if self.topic is None or self.radius is None:
            return
        x_task, y_task = self.tasks[0], self.tasks[1]
        x = x_task.feedback.position_deg - x_task.reference_offset_deg
        y = y_task.feedback.position_deg - y_task.reference_offset_deg
        error = float(contour_error(x, y, self.radius))
        t_s = x_task.t_s
        self.topic.log(t_ns, (t_s, x, y, error))
        if t_s >= self.settle_s - 1e-12:
            self.counted += 1
            self.sum_squares += error * error
            self.max_error = max(self.max_error, abs(error))

    def kpis(self) -> dict[str, Any]:
        return {"radius_deg": self.radius,
                "max_contour_error_deg": self.max_error if self.counted else None,
                "rms_contour_error_deg": math.sqrt(self.sum_squares / self.counted)
                if self.counted else None}


class AxesExperiment(ServoExperiment):
    """``hil servo run --axes``: the single-axis run's plan, several drives and tasks. A
    ``--limit`` names a KPI of an axis (``axes.x.max_error_deg``), of the path
    (``contour.max_contour_error_deg``) or of the run; a per-tick signal limit holds on every
    axis."""

    kpi_names = ("axes", "contour", "ticks", "sync_cycles", "wall_s", "realtime_factor",
                 "faults")

    def __init__(self, options: ServoRunOptions, axes: tuple[AxisSpec, ...]) -> None:
        super().__init__(options)
        self.axes = axes
        self.groups: AxisGroups | None = None
        self.emulator: LockstepDrive | None = None
        self.tasks: list[ServoTask] = []
        self.bus_task: BusCycle | None = None

    def parse_reference(self) -> Scenario:
        """Every axis' scenario: a circle's axis each, or ``--reference`` for all; the
        first axis' is the run's."""
        options = self.options
        circle = parse_circle(options.reference)
        self.radius = circle[0] if circle is not None else None
        if circle is None:
            self.scenarios = [super().parse_reference()] * len(self.axes)
        elif len(self.axes) != 2:
            raise UsageError(f"--reference {options.reference}: a circle needs two axes, "
                             f"--axes names {len(self.axes)}")
        else:
            self.scenarios = [Scenario(CircleAxis(circle[0], circle[1], i)) for i in range(2)]
        return self.scenarios[0]

    def plan(self) -> RunPlan:
        options = self.options
        names = [axis.name for axis in self.axes]
        for key in options.params:
            axis, dot, _ = key.partition(".")
            if dot and axis not in names:
                raise UsageError(f"--param {key}: no axis {axis!r} (the axes: "
                                 f"{', '.join(names)}); NAME.KEY=VALUE sets KEY for axis NAME")
        if options.can_log:
            raise UsageError("--can-log is not available with --axes yet")
        plan = super().plan()
        self.buses = plan_buses(self.axes, self.drive_url, self.drive)
        for bus in self.buses:
            if not bus.plan.fits and bus.url != EMULATED:  # the in-process bus has no bitrate
                raise UsageError(f"the bus plan does not fit ({bus.url}): "
                                 f"{bus.plan.problem(self._period_note(bus.plan))} (see "
                                 f"'hil drive plan --axes {len(bus.axes)}')")
            if options.realtime and bus.url == EMULATED:
                raise UsageError("--realtime --axes needs a bus: start the emulated drives with "
                                 "`hil emulate drive --socketcand 127.0.0.1:0 --node 1 --node "
                                 "2` and pass its URL as --drive")
        self.bus_of = {axis.name: bus.url for bus in self.buses for axis in bus.axes}
        plan.config["servo"]["axes"] = [
            {"name": a.name, "node": a.node, "bus": self.bus_of[a.name]} for a in self.axes]
        return replace(plan, label=f"{plan.label} on {len(self.axes)} axes",
                       devices=self._bus_devices())

    def _period_note(self, plan: BusPlan) -> str:
        """Which longer period the run's controller runs at (when its periods can be listed):
        the shortest the plan fits."""
        periods = cycle_periods_of(self.factory)
        if not isinstance(periods, (range, tuple, list, set, frozenset)):
            return ""
        longer = [p for p in sorted(periods) if p >= plan.min_period_us]
        label = self.options.label
        return (f"; controller {label!r} runs at {longer[0]} us" if longer else
                f"; controller {label!r} runs at no period that long")

    def _bus_devices(self) -> tuple[tuple[str, str], ...]:
        """Every bus of the run but the in-process ones, locked for the run."""
        return tuple(("drive bus", bus.url) for bus in self.buses
                     if scheme_of(bus.url) not in (EMULATED, "virtual"))

    def open_devices(self, clock: Clock, on_event: EventBuffer) -> None:
        options, drive = self.options, self.drive
        masters: dict[str, CanDriveMaster] = {}
        groups: list[AxisGroup] = []
        try:
            for bus in self.buses:
                nodes = [axis.node for axis in bus.axes]
                master_clock = None
                if bus.url == EMULATED:
                    self.emulator = master_clock = LockstepDrive(drive.emulator, node_ids=nodes)
                    link = CanLink(self.emulator.master_bus)
                else:
                    spec = parse_can_url(bus.url, drive.master.channel)
                    link = CanLink(open_can_bus(spec, drive.master.bitrate))
                axis_bus = AxisBus(link, nodes, master_heartbeat_id=drive.master.heartbeat_id)
                on_bus = [CanDriveMaster(axis_bus.node_link(axis.node),
                                         axis.master(drive.master), on_event=on_event,
                                         clock=master_clock, url=f"{bus.url} axis {axis.name}")
                          for axis in bus.axes]
                masters.update(zip((axis.name for axis in bus.axes), on_bus, strict=True))
                groups.append(AxisGroup(axis_bus, on_bus))
            self.groups = AxisGroups(groups)
            self.masters = [masters[axis.name] for axis in self.axes]  # the run's order
            for master in self.masters:
                if master.config.lockstep:  # over a bus: one clock on both sides of the wire
                    share_lockstep_time(master, on_event)
                if options.reset_fault:
                    master.fault_reset()
                master.open()
        except BaseException:
            if self.groups is None:
                self.groups = AxisGroups(groups)
            self.close_devices()
            raise

    def build_controller(self, session: Session) -> None:
        """One controller per axis, with that axis' reference and parameters (the common
        ones, and ``NAME.KEY`` laid over them for axis NAME); a multi-axis controller
        (``multi_axis = True``) once, with every axis' reference, shared by the axes."""
        self.references = [PlacedReference(scenario.reference, relative=self.options.from_here)
                           for scenario in self.scenarios]
        if getattr(self.factory, "multi_axis", False):
            whole = build_controller(self.factory, self.options.label, self.references,
                                     dict(self.params), method="step", application="servo")
            shared = SharedStep(whole, self.tasks, self.options.label)
            self.controllers: list[Any] = [AxisShare(shared, i) for i in range(len(self.axes))]
            return
        self.controllers = [
            make_controller(self.options, scenario, session, self.axis_params(axis.name),
                            self.factory, min(self.settings.umax_ma, master.current_limit_ma),
                            reference=reference, period_s=self.period_s)
            for axis, scenario, reference, master in zip(
                self.axes, self.scenarios, self.references, self.masters, strict=True)]

    def axis_params(self, name: str) -> dict[str, Any]:
        common = {k: v for k, v in self.params.items() if "." not in k}
        return common | {k.partition(".")[2]: v for k, v in self.params.items()
                         if k.startswith(f"{name}.")}

    def start(self, session: Session) -> None:
        groups, options = self.groups, self.options
        assert groups is not None
        for master in self.masters:
            master.configure()
        session.recorder.metadata("drive", {"json": json.dumps(
            {axis.name: master.describe() for axis, master in zip(self.axes, self.masters,
                                                                  strict=True)})})
        for master in self.masters:
            master.enable()
        groups.cycle_together()
        session.add_component(groups)
        session.recorder.metadata("bus_plan", {"json": json.dumps({"buses": [
            {"url": bus.url, "axis_names": [axis.name for axis in bus.axes],
             **bus.plan.summary()} for bus in self.buses]})})
        for bus in self.buses:
            if not bus.plan.fits:
                message = (f"on a real bus this would not fit: "
                           f"{bus.plan.problem(self._period_note(bus.plan))}")
                warn(message)
                session.event("bus.plan", message, level="warning", source="bus", url=bus.url)
        budget = controller_budget(options.controller_budget_s, options.realtime,
                                   STEP_BUDGET_S)
        for axis, master, controller, scenario, reference in zip(
                self.axes, self.masters, self.controllers, self.scenarios, self.references,
                strict=True):
            task = ServoTask(session, master, controller, scenario, reference=reference,
                             label=options.label,
                             settle_s=options.settle_s,
                             prediction_every=options.prediction_period, budget_s=budget,
                             safety=SafetyMonitor(self.drive.safety, self.period_s),
                             watch=self.watch, axis=axis.name)
            self.tasks.append(task)
            session.add_task(task)
        self.bus_task = BusCycle(session, groups, self.tasks, self.radius, options.settle_s)
        session.add_task(self.bus_task)

    def finish(self, session: Session) -> None:
        for task in self.tasks:
            if task.safety.stopped is not None:
                raise SafetyStopError(task.safety.stopped)

    def close_devices(self) -> None:
        if self.groups is not None:
            self.groups.close()
            self.groups = None
        if self.emulator is not None:
            self.emulator.close()
            self.emulator = None

    def kpis(self, session: Session, wall_s: float, error: HilError | None) -> dict[str, Any]:
        options, loop = self.options, session.loop
        ticks = self.tasks[0].stats.ticks if self.tasks else 0
        axes = {}
        for axis, task in zip(self.axes, self.tasks, strict=True):
            tracking = task.stats.kpis(reference_amplitude(task.scenario))
            master = task.master
            tracking.update({"node": axis.node, "bus": self.bus_of[axis.name],
                             "stale_feedback": task.stale,
                             "clamped_commands": master.stats.clamped_commands,
                             "current_limit_mA": master.current_limit_ma,
                             "late_frames": master.stats.late_frames,
                             "emcy": master.stats.emcy})
            axes[axis.name] = tracking
        kpis: dict[str, Any] = {
            "controller": options.label, "axes": axes, "ticks": ticks,
            "cycle_period_us": round(self.period_s * 1e6),
            "mcap": options.recording.first_file(self.out), "reference": options.reference,
            "drive": self.drive_url, "buses": [bus.url for bus in self.buses],
            "clock": session.clock.mode,
            "umax_mA": self.settings.umax_ma, "settle_s": options.settle_s,
            "sync_cycles": self.bus_task.cycles if self.bus_task is not None else 0,
            "wall_s": round(wall_s, 4),
            "realtime_factor": realtime_factor(ticks, loop),
            "stop_reason": loop.stop_reason}
        if self.bus_task is not None and self.radius is not None:
            kpis["contour"] = self.bus_task.kpis()
        stale = sum(a["stale_feedback"] for a in axes.values())
        emcy = sum(a["emcy"] for a in axes.values())
        kpis["faults"] = {"stale_feedback": stale, "emcy": emcy,
                          "late_frames": sum(a["late_frames"] for a in axes.values())}
        kpis["disturbed"] = bool(stale or emcy)
        return kpis


def run_any(options: ServoRunOptions) -> RunResult:
    """A servo session on one axis (:func:`hil.servo.run.run_servo`), or on several when
    ``options.axes`` or the drive config's ``[[axis]]`` name them."""
    configured = resolve_servo(options).drive.axes
    if not options.axes and not configured:
        return run_servo(options)
    axes = parse_axes(options.axes) if options.axes else configured
    return run_experiment(AxesExperiment(options, axes))
