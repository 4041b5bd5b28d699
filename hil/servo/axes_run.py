"""``hil servo run --axes x=1,y=2``: several axes on one bus, one SYNC per tick.

Each axis is one drive (its node id) with its own master on one
:class:`~drivers.canopen.axes.AxisBus`, its own controller (the run's, built once per axis
with that axis' reference) and its own servo task (topics ``/axis/NAME/command``,
``/axis/NAME/feedback``, ``/axis/NAME/prediction``). The tick's phases run axis by axis, and a
bus task comes last: its write puts every axis' RPDO and one SYNC on the bus, its record logs
the contour error of a path (``/path/contour``). A stop of any kind (a safety limit, a fault,
Ctrl-C) stops every axis in the same cycles (:func:`~drivers.canopen.master.stop_together`).

References: ``--reference`` as for one axis (every axis the same), or the path
``circle:radius=R,feed=F`` for two axes (a circular test, ISO 230-4: R in degrees of each
axis, F in degrees per second along the path). Parameters: ``--param KEY=V`` for every axis,
``--param NAME.KEY=V`` for axis NAME (a gain mismatch between axes, say).
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from typing import Any

import numpy as np

from controllers.servo.model import SAMPLE_PERIOD_S
from controllers.servo.references import CircleAxis, Scenario, contour_error, parse_circle
from drivers.can_bus_time import plan_bus
from drivers.canopen import CanDriveMaster, CanLink, open_can_bus, parse_can_url
from drivers.canopen.axes import AxisBus, AxisGroup
from drivers.canopen.master import axis_traffic
from emulators.drive.runners import LockstepDrive
from hil.core.clock import Clock
from hil.core.errors import ControllerError, HilError, SafetyStopError, UsageError
from hil.core.loop import Task
from hil.core.plugins import build_controller
from hil.core.run import EventBuffer, RunPlan, RunResult, controller_budget, run_experiment
from hil.core.session import Session
from hil.servo.config import AXIS_NAME, EMULATED, AxisSpec, check_axes
from hil.servo.run import (
    STEP_BUDGET_S,
    ServoExperiment,
    ServoRunOptions,
    drive_settings,
    make_controller,
    realtime_factor,
    run_servo,
)
from hil.servo.safety import SafetyMonitor
from hil.servo.task import ServoTask
from hil.servo.tracking import reference_amplitude

CONTOUR_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.Contour",
    "description": "A path's contour error: distance of the axes' measured point from the "
                   "path (> 0 outside a circle).",
    "properties": {
        "t_s": {"type": "number"},
        "x_deg": {"type": "number"},
        "y_deg": {"type": "number"},
        "contour_error_deg": {"type": "number", "x-cdr": "float32"},
    },
}


def parse_axes(text: str) -> tuple[AxisSpec, ...]:
    """``x=1,y=2`` -> the axes, in order; a clear error for anything else."""
    axes = []
    for item in filter(None, (part.strip() for part in text.split(","))):
        name, eq, node = item.partition("=")
        if not eq or not AXIS_NAME.fullmatch(name) or not node.isdigit() or \
                not 1 <= int(node) <= 127:
            raise UsageError(f"--axes {text!r}: {item!r} is not NAME=NODE (a lower-case name, "
                             "a CANopen node id 1..127), e.g. --axes x=1,y=2")
        axes.append(AxisSpec(name, int(node)))
    return check_axes(tuple(axes), f"--axes {text!r}")


class SharedStep:
    """A multi-axis controller (``multi_axis = True``, built as ``Class(references,
    params)``, ``step(positions_deg: np.ndarray, t_s) -> currents_mA``) stepped once a tick
    with every axis' position (all read by then), its currents kept for the axes' tasks."""

    def __init__(self, whole: Any, tasks: list[ServoTask], label: str) -> None:
        self.whole, self.tasks, self.label = whole, tasks, label
        self._t_s: float | None = None
        self._currents = np.zeros(0)

    def currents(self, t_s: float) -> np.ndarray:
        if self._t_s != t_s:  # the first axis of this tick steps the controller
            positions = np.array([task.feedback.position_deg % 360.0 for task in self.tasks])
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


class BusCycle(Task):
    """Last in the tick: the cycle on the bus (every axis' RPDO, one SYNC), then the path's
    contour error."""

    def __init__(self, session: Session, bus: AxisBus, tasks: list[ServoTask],
                 radius: float | None, settle_s: float) -> None:
        super().__init__("bus")
        self.bus, self.tasks, self.radius = bus, tasks, radius
        self.settle_s = settle_s
        self.topic = session.topic("/path/contour", CONTOUR_SCHEMA, high_rate=True) \
            if radius is not None else None
        self.max_error = 0.0
        self.sum_squares = 0.0
        self.counted = 0
        self.cycles = 0  # cycles put on the bus while ticking

    def write(self, t_ns: int) -> None:
        self.bus.end_cycle()
        self.cycles += 1

    def record(self, t_ns: int) -> None:
        if self.topic is None or self.radius is None:
            return
        x_task, y_task = self.tasks[0], self.tasks[1]
        x, y = x_task.feedback.position_deg, y_task.feedback.position_deg
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
        self.group: AxisGroup | None = None
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
        url = options.drive or self.drive.bus_url
        master = self.drive.master
        self.bus_plan = plan_bus(master.bitrate, master.cycle_period_s,
                                 [axis_traffic(master, axis.name) for axis in self.axes],
                                 master_heartbeat_s=master.heartbeat_period_ms / 1e3)
        if not self.bus_plan.fits and url != EMULATED:  # the in-process bus has no bitrate
            raise UsageError(f"the bus plan does not fit ({url}): {self.bus_plan.problem()} "
                             "(see 'hil drive plan')")
        if options.realtime and url == EMULATED:
            raise UsageError("--realtime --axes needs a bus: start the emulated drives with "
                             "`hil emulate drive --socketcand 127.0.0.1:0 --node 1 --node 2` "
                             "and pass its URL as --drive")
        plan.config["servo"]["axes"] = [{"name": a.name, "node": a.node} for a in self.axes]
        return replace(plan, label=f"{plan.label} on {len(self.axes)} axes")

    def open_devices(self, clock: Clock, on_event: EventBuffer) -> None:
        options, drive = self.options, self.drive
        nodes = [axis.node for axis in self.axes]
        url = options.drive or drive.bus_url
        if url == EMULATED:
            self.emulator = LockstepDrive(drive.emulator, node_ids=nodes)
            link = CanLink(self.emulator.master_bus)
        else:
            spec = parse_can_url(url, drive.master.channel)
            link = CanLink(open_can_bus(spec, drive.master.bitrate))
        bus = AxisBus(link, nodes, master_heartbeat_id=drive.master.heartbeat_id)
        masters = [CanDriveMaster(bus.node_link(axis.node),
                                  replace(drive.master, node_id=axis.node), on_event=on_event,
                                  clock=self.emulator, url=f"{url} axis {axis.name}")
                   for axis in self.axes]
        self.group = AxisGroup(bus, masters)
        try:
            for master in masters:
                if options.reset_fault:
                    master.clear_fault()
                master.open()
        except BaseException:
            self.close_devices()
            raise

    def build_controller(self, session: Session) -> None:
        """One controller per axis, with that axis' reference and parameters (the common
        ones, and ``NAME.KEY`` laid over them for axis NAME); a multi-axis controller
        (``multi_axis = True``) once, with every axis' reference, shared by the axes."""
        if getattr(self.factory, "multi_axis", False):
            references = [scenario.reference for scenario in self.scenarios]
            whole = build_controller(self.factory, self.options.label, references,
                                     dict(self.params), method="step", application="servo")
            shared = SharedStep(whole, self.tasks, self.options.label)
            self.controllers: list[Any] = [AxisShare(shared, i) for i in range(len(self.axes))]
            return
        self.controllers = [
            make_controller(self.options, scenario, session, self.axis_params(axis.name),
                            self.factory)
            for axis, scenario in zip(self.axes, self.scenarios, strict=True)]

    def axis_params(self, name: str) -> dict[str, Any]:
        common = {k: v for k, v in self.params.items() if "." not in k}
        return common | {k.partition(".")[2]: v for k, v in self.params.items()
                         if k.startswith(f"{name}.")}

    def start(self, session: Session) -> None:
        group, options = self.group, self.options
        assert group is not None
        for master in group.masters:
            master.configure()
        session.recorder.metadata("drive", {"json": json.dumps(
            {axis.name: master.describe() for axis, master in zip(self.axes, group.masters,
                                                                  strict=True)})})
        for master in group.masters:
            master.enable()
        group.bus.cycle_together(True)
        session.add_component(group)
        session.recorder.metadata("bus_plan", {"json": json.dumps(self.bus_plan.summary())})
        if not self.bus_plan.fits:
            session.event("bus.plan", f"on a real bus this would not fit: "
                          f"{self.bus_plan.problem()}", level="warning", source="bus")
        budget = controller_budget(options.controller_budget_s, options.realtime,
                                   STEP_BUDGET_S)
        for axis, master, controller, scenario in zip(self.axes, group.masters,
                                                      self.controllers, self.scenarios,
                                                      strict=True):
            task = ServoTask(session, master, controller, scenario, label=options.label,
                             settle_s=options.settle_s,
                             prediction_every=options.prediction_period, budget_s=budget,
                             safety=SafetyMonitor(self.drive.safety, SAMPLE_PERIOD_S),
                             watch=self.watch, axis=axis.name)
            self.tasks.append(task)
            session.add_task(task)
        self.bus_task = BusCycle(session, group.bus, self.tasks, self.radius, options.settle_s)
        session.add_task(self.bus_task)

    def finish(self, session: Session) -> None:
        for task in self.tasks:
            if task.safety.stopped is not None:
                raise SafetyStopError(task.safety.stopped)

    def close_devices(self) -> None:
        if self.group is not None:
            self.group.close()
            self.group = None
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
            tracking.update({"node": axis.node, "stale_feedback": task.stale,
                             "clamped_commands": master.stats.clamped_commands,
                             "late_frames": master.stats.late_frames,
                             "emcy": master.stats.emcy})
            axes[axis.name] = tracking
        kpis: dict[str, Any] = {
            "controller": options.label, "axes": axes, "ticks": ticks,
            "mcap": options.recording.first_file(self.out), "reference": options.reference,
            "drive": options.drive or self.drive.bus_url, "clock": session.clock.mode,
            "umax_mA": options.umax, "settle_s": options.settle_s,
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
    configured = drive_settings(options).axes
    if not options.axes and not configured:
        return run_servo(options)
    axes = parse_axes(options.axes) if options.axes else configured
    return run_experiment(AxesExperiment(options, axes))
