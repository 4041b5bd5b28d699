"""The servo scenario (``hil servo run``): a controller closing the loop through the CAN drive
link on one axis or several, as the run pipeline (:mod:`hil.core.run`) drives it.

One pipeline for every run: :class:`ServoExperiment` takes the run's axes (``--axes``,
drive.toml's ``[[axis]]``, or, naming none, the one axis of ``[master]``), opens each bus's
drives through the :data:`~hil.servo.rig.DRIVES` registry (the emulator in lockstep by
default), builds a controller per axis, enables the drives and runs one
:class:`~hil.servo.task.ServoTask` per axis at the base period T = ``master.cycle_period_us``
(500 us by default, the published axis model's; the controller must run at it). Recorded per
tick and axis: the command (reference, command, error, controller compute time, solver path),
the feedback (what the drive reported) and the prediction; faults and fallbacks go to
``/events``. The one axis of a run that names none records ``/drive/command``,
``/drive/feedback`` and ``/mpc/prediction``; named axes record ``/axis/NAME/...``, and the bus
loop's one task (:class:`~hil.servo.axes.AxesTick`) ticks every axis, ends every bus's cycle and
records a path's contour.

KPIs (:mod:`hil.servo.tracking`, the ``--json`` document): the tracking error after
``settle_s``, the controller's step time, and ``deadline_misses``, which counts, in real
time, ticks the loop skipped plus ticks whose command left after the next tick's deadline
(always 0 in lockstep, where slow compute costs no virtual time). Named axes nest theirs
under ``axes.NAME``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from typing import Any, cast

from hil.controllers.base import (
    OUTPUT_UNITS,
    CountsFallbacks,
    ServoController,
    horizons_of,
    output_of,
    position_input_of,
    solver_of,
)
from hil.controllers.errors import ControllerSetupError
from hil.controllers.servo.references import (
    PlacedReference,
    Reference,
    Scenario,
)
from hil.core.clock import Clock
from hil.core.loop import FixedRateLoop
from hil.core.notice import warn
from hil.core.plugins import (
    build_controller,
    controller_factory,
)
from hil.core.run import (
    EventBuffer,
    Experiment,
    RunResult,
    TunerStarted,
    controller_budget,
    run_experiment,
)
from hil.core.session import Session
from hil.core.tuning import Tuner, add_controller
from hil.drivers.canopen import CanDriveMaster
from hil.errors import HilError, SafetyStopError
from hil.servo.axes import AxesTick, AxisShare, SharedStep, carries_can
from hil.servo.builtin import ServoContext
from hil.servo.config import stricter_safety
from hil.servo.drives import RunDrives
from hil.servo.kpis import AxesKpis, AxisKpis, ServoKpis, no_tracking
from hil.servo.motion import home_axis
from hil.servo.options import ServoRunOptions
from hil.servo.plan import ServoPlan, ServoState, plan_servo
from hil.servo.rig import keep_lockstep_time, open_drives, reach, tell_notices
from hil.servo.safety import SafetyMonitor
from hil.servo.settings import resolve_servo, run_output
from hil.servo.task import ServoTask, check_disturbance_object
from hil.servo.tracking import reference_amplitude
from hil.servo.tunables import add_servo_limits

# a step longer than this stops the run: far beyond any real controller's step (the MPC takes
# ~50 us), and long enough that a stall of the machine (a collector pass, a preempted VM) does
# not pass for a hung controller; the loop counts the ticks a slow step costs in real time
STEP_BUDGET_S = 0.25


def make_controller(options: ServoRunOptions, scenario: Scenario, session: Any = None,
                    params: Mapping[str, Any] | None = None,
                    factory: Callable[..., Any] | None = None,
                    umax_ma: float | None = None, *,
                    reference: Reference | None = None,
                    period_s: float | None = None,
                    output: str | None = None) -> ServoController:
    """The controller of the run, built from its spec as ``factory(reference, params)``
    (``context=`` too when the factory takes it); ``factory``: already loaded and checked;
    ``umax_ma``: its current bound (default: the run's, as :func:`resolve_servo` gives it);
    ``reference``: the run's (placed where the axis starts), else the scenario's;
    ``period_s``: the cycle period it is stepped at (default: the run's); ``output``: what it
    is to return (default: what the drive's mode takes). A ``position_input`` other than
    wrapped or unwrapped, or another ``output``, is a ConfigError naming it."""
    if umax_ma is None or period_s is None or output is None:
        settings = resolve_servo(options)
        umax_ma = settings.umax_ma if umax_ma is None else umax_ma
        period_s = settings.drive.master.cycle_period_s if period_s is None else period_s
        output = run_output(settings.drive) if output is None else output
    context = ServoContext(options.ht, options.hu, options.hp, options.ert, umax_ma, session,
                           period_s, output)
    values = dict(options.params if params is None else params)
    label = options.label
    if factory is None:
        factory, label = controller_factory(options.controller, scenario.reference, values,
                                            method="step", application="servo")
    controller = build_controller(factory, label, scenario.reference if reference is None
                                  else reference, values, method="step",
                                  application="servo", context=context)
    position_input_of(controller, label)
    if (returned := output_of(controller, label)) != output:
        raise ControllerSetupError(f"controller {label!r} returns a {returned}, and the drive "
                                   f"takes a {output} [{OUTPUT_UNITS[output]}] (its mode)")
    return cast(ServoController, controller)


def run_servo(options: ServoRunOptions,
              on_started: Callable[[CanDriveMaster], None] | None = None, *,
              tuner_started: TunerStarted | None = None) -> RunResult:
    """Run one servo session, on one axis or several; ``on_started(master)`` is called with
    the first axis' master once the drives are enabled, ``tuner_started(tuner)`` with the
    run's tuner before the first tick (:mod:`hil.core.tuning`).

    Drive errors (fault, link lost) stop the loop; the drives are put in their safe state, the
    session file is finished with the KPIs so far, and the error is raised with its path."""
    return run_experiment(ServoExperiment(options, on_started), tuner_started=tuner_started)


def can_log_path(path: str | None, bus: int) -> str | None:
    """The ``--can-log`` file of the run's ``bus``-th bus (from 0): the path itself for the
    first, ``STEM-busN.SUFFIX`` for the N-th after it."""
    if path is None or bus == 0:
        return path
    stem, dot, suffix = path.rpartition(".")
    return f"{stem}-bus{bus + 1}.{suffix}" if dot and "/" not in suffix else \
        f"{path}-bus{bus + 1}"


class ServoExperiment(Experiment[ServoPlan]):
    """``hil servo run`` as the run pipeline drives it, on one axis or several: its frozen
    :class:`~hil.servo.plan.ServoPlan` (``planned``) and what each step opened or built
    (``state``). A ``--limit`` names a KPI of the run; with named axes, of an axis
    (``axes.x.max_error_deg``), of the path (``contour.max_contour_error_deg``) or of the run;
    a per-tick signal limit holds on every axis."""

    def __init__(self, options: ServoRunOptions,
                 on_started: Callable[[CanDriveMaster], None] | None = None) -> None:
        self.options = options
        self.on_started = on_started
        self.state = ServoState()

    def plan(self) -> ServoPlan:
        return plan_servo(self.options)

    def open_devices(self, clock: Clock, on_event: EventBuffer) -> None:
        """Every bus's drives, reached and in a known state (not enabled)."""
        options, plan, state = self.options, self.planned, self.state
        for kind, message in plan.settings.notices:
            warn(message)
            on_event(kind, message, level="warning", source="settings")
        try:
            masters: dict[str, CanDriveMaster] = {}
            for i, bus in enumerate(plan.buses):
                opened = open_drives(bus.url, plan.drive, bus.axes, on_event=on_event,
                                     realtime=options.realtime,
                                     can_log=can_log_path(options.can_log, i))
                state.drives.add(opened)
                masters.update(zip((axis.name for axis in bus.axes), opened.masters,
                                   strict=True))
            state.masters = [masters[axis.name] for axis in plan.axes]
            for master in state.masters:
                reach(master, on_event, options.reset_fault,
                      "--umax" if options.umax is not None else "master.current_limit_mA")
        except BaseException:
            self.close_devices()
            raise

    def build_controller(self, session: Session) -> None:
        """One controller per axis, with that axis' reference (placed where the axis stands
        when its drive is enabled: its servo task places it, before the first step) and
        parameters (the common ones, and ``NAME.KEY`` laid over them for axis NAME); a
        multi-axis controller (``multi_axis = True``) once, with every axis' reference,
        shared by the axes."""
        options, plan, state = self.options, self.planned, self.state
        state.references = [PlacedReference(scenario.reference, relative=options.from_here,
                                            absolute=options.home)
                            for scenario in plan.scenarios]
        if not plan.lone and getattr(plan.factory, "multi_axis", False):
            whole = build_controller(plan.factory, options.label, state.references,
                                     dict(plan.params), method="step", application="servo")
            shared = SharedStep(whole, state.tasks, options.label)
            state.controllers = [AxisShare(shared, i) for i in range(len(plan.axes))]
            return
        state.controllers = [
            make_controller(options, scenario, session, plan.axis_params(axis.name),
                            plan.factory, plan.umax_for(master),
                            reference=reference, period_s=plan.base_period_s,
                            output=run_output(plan.drive))
            for axis, scenario, reference, master in zip(
                plan.axes, plan.scenarios, state.references, state.masters, strict=True)]

    def start(self, session: Session) -> None:
        options, plan, state = self.options, self.planned, self.state
        if options.home:
            for master in state.masters:
                self._home(session, master)
        for master in state.masters:
            master.configure()
            tell_notices(master)
        described = {axis.name: master.describe()
                     for axis, master in zip(plan.axes, state.masters, strict=True)}
        session.recorder.metadata("drive", {"json": json.dumps(
            described[plan.axes[0].name] if plan.lone else described)})
        if any(scenario.disturbance is not None for scenario in plan.scenarios):
            for master in state.masters:  # by SDO, before the axes' cycles are held together
                check_disturbance_object(master)
        for master in state.masters:
            master.enable()
            keep_lockstep_time(master, session.event)
        state.drives.cycle_together()
        session.add_component(state.drives)
        if not plan.lone:
            self._record_bus_plans(session)
        budget = controller_budget(options.controller_budget_s, options.realtime,
                                   STEP_BUDGET_S)
        for axis, master, controller, scenario, reference in zip(
                plan.axes, state.masters, state.controllers, plan.scenarios, state.references,
                strict=True):
            task = ServoTask(session, master, controller, scenario, reference=reference,
                             label=options.label, settle_s=options.settle_s,
                             prediction_every=options.prediction_period, budget_s=budget,
                             safety=SafetyMonitor(
                                 stricter_safety(plan.drive.safety, axis.safety),
                                 plan.base_period_s, axis=None if plan.lone else axis.name),
                             watch=plan.watch, axis=None if plan.lone else axis.name)
            state.tasks.append(task)
        if plan.lone:
            session.add_task(state.tasks[0])
        else:
            state.axes_tick = AxesTick(session, state.drives, state.tasks, plan.radius,
                                       options.settle_s)
            session.add_task(state.axes_tick)
        if self.on_started is not None:
            self.on_started(state.masters[0])

    def _home(self, session: Session, master: CanDriveMaster) -> None:
        """``--home``: the axis homed (HM) before the run's mode is configured."""
        at_home = home_axis(master, self.planned.drive.master.profile.homing_timeout_s)
        session.event("drive.homed", f"drive node {master.node_id} homed: at "
                      f"{at_home.position_deg:.4f} deg", source=f"drive{master.node_id}",
                      position_deg=at_home.position_deg)

    def tunables(self, tuner: Tuner) -> None:
        """One axis: its controller's parameters (``controller.NAME``) and its safety
        limits (``safety.NAME``, only stricter). Several axes: none yet."""
        if not self.planned.lone or not self.state.tasks:
            return
        task = self.state.tasks[0]
        if add_controller(tuner, task.controller):
            tuner.add_listener(lambda result: task.controller_changed()
                               if result.name.startswith("controller.") else None)
        add_servo_limits(tuner, task.safety, task.master)

    def _record_bus_plans(self, session: Session) -> None:
        """Every CAN bus's plan as metadata; one that would not fit a real bus, as a
        warning."""
        plan = self.planned
        buses = [bus for bus in plan.buses if carries_can(bus.url)]
        session.recorder.metadata("bus_plan", {"json": json.dumps({"buses": [
            {"url": bus.url, "axis_names": [axis.name for axis in bus.axes],
             **bus.plan.summary()} for bus in buses]})})
        for bus in buses:
            if not bus.plan.fits:
                message = (f"on a real bus this would not fit: "
                           f"{bus.plan.problem(plan.period_note(bus.plan))}")
                warn(message)
                session.event("bus.plan", message, level="warning", source="bus", url=bus.url)

    def finish(self, session: Session) -> None:
        """A safety stop ends the run as an error (the drives are already in their safe
        state)."""
        for task in self.state.tasks:
            if task.safety.stopped is not None:
                raise SafetyStopError(task.safety.stopped)

    def close_devices(self) -> None:
        drives, self.state.drives = self.state.drives, RunDrives()
        drives.close()

    def kpis(self, session: Session, wall_s: float, error: HilError | None
             ) -> ServoKpis | AxesKpis:
        """The ``--json`` document: the documented keys first, then context."""
        return self._lone_kpis(session, wall_s) if self.planned.lone else \
            self._axes_kpis(session, wall_s)

    def _lone_kpis(self, session: Session, wall_s: float) -> ServoKpis:
        options, plan, state, loop = self.options, self.planned, self.state, session.loop
        task = state.tasks[0] if state.tasks else None
        master = state.masters[0] if state.masters else None
        ticks = task.stats.ticks if task is not None else 0
        kpis = ServoKpis(
            controller=options.label,
            deadline_misses=(loop.skipped_ticks + task.late_writes
                             if task is not None and options.realtime else 0),
            ticks=ticks, cycle_period_us=round(plan.base_period_s * 1e6),
            mcap=options.recording.first_file(plan.session_path), reference=options.reference,
            drive=master.url if master is not None else plan.settings.drive_url,
            clock=session.clock.mode,
            umax_ma=plan.umax_for(master) if master is not None else plan.settings.umax_ma,
            current_limit_ma=master.current_limit_ma if master is not None else None,
            settle_s=options.settle_s,
            stale_feedback=task.stale if task is not None else 0,
            clamped_commands=master.stats.clamped_commands if master is not None else 0,
            wall_s=round(wall_s, 4), realtime_factor=realtime_factor(ticks, loop),
            stop_reason=loop.stop_reason,
        ).lay(task.stats.kpis(reference_amplitude(plan.scenarios[0]))
                        if task is not None else no_tracking())
        controller = task.controller if task is not None else None
        if task is not None and not task.currents:
            kpis.set_point = task.output
        horizons = horizons_of(controller)
        if horizons is not None:
            kpis.ert, kpis.ht, kpis.hu, kpis.hp = (horizons.ert, horizons.ht, horizons.hu,
                                                   horizons.hp)
            solver = solver_of(controller)
            if solver is not None:
                kpis.solver_paths = dict(solver.counts)
            if isinstance(controller, CountsFallbacks):
                kpis.empc_fallbacks = int(controller.fallbacks)
        kpis.faults = {"stale_feedback": kpis.stale_feedback,
                       "late_frames": master.stats.late_frames if master is not None else 0,
                       "emcy": master.stats.emcy if master is not None else 0}
        kpis.disturbed = bool(kpis.stale_feedback or kpis.faults["emcy"])
        return kpis

    def _axes_kpis(self, session: Session, wall_s: float) -> AxesKpis:
        options, plan, state, loop = self.options, self.planned, self.state, session.loop
        ticks = state.tasks[0].stats.ticks if state.tasks else 0
        bus_of = plan.bus_of
        axes = {}
        for axis, task in zip(plan.axes, state.tasks, strict=False):
            master = task.master
            axes[axis.name] = AxisKpis(
                **vars(task.stats.kpis(reference_amplitude(task.scenario))),
                node=axis.node, bus=bus_of[axis.name], stale_feedback=task.stale,
                clamped_commands=master.stats.clamped_commands,
                current_limit_ma=master.current_limit_ma,
                late_frames=master.stats.late_frames, emcy=master.stats.emcy)
        stale = sum(a.stale_feedback for a in axes.values())
        emcy = sum(a.emcy for a in axes.values())
        return AxesKpis(
            controller=options.label, axes=axes, ticks=ticks,
            cycle_period_us=round(plan.base_period_s * 1e6),
            mcap=options.recording.first_file(plan.session_path), reference=options.reference,
            drive=plan.settings.drive_url, buses=[bus.url for bus in plan.buses],
            clock=session.clock.mode, umax_ma=plan.settings.umax_ma,
            settle_s=options.settle_s,
            sync_cycles=state.axes_tick.cycles if state.axes_tick is not None else 0,
            wall_s=round(wall_s, 4), realtime_factor=realtime_factor(ticks, loop),
            stop_reason=loop.stop_reason,
            contour=state.axes_tick.kpis()
            if state.axes_tick is not None and plan.radius is not None else None,
            faults={"stale_feedback": stale, "emcy": emcy,
                    "late_frames": sum(a.late_frames for a in axes.values())},
            disturbed=bool(stale or emcy))


def realtime_factor(ticks: int, loop: FixedRateLoop) -> float | None:
    """Simulated time over the wall time the loop spent ticking (the writer's start and the
    safe stop are not the loop's pace); None before a tick."""
    if loop.ticking_s <= 0:
        return None
    return round(ticks * (loop.base_period_ns / 1e9) / loop.ticking_s, 2)

