"""The servo scenario (``hil servo run``): a controller closing the loop through the CAN drive
link, as the run pipeline (:mod:`hil.core.run`) drives it.

:class:`ServoExperiment` opens the drive (the emulator in lockstep by default), builds the
controller, enables the drive and runs one :class:`~hil.servo.task.ServoTask` at the base
period T = ``master.cycle_period_us`` (500 us by default, the published axis model's; the
controller must run at it). Recorded per tick: ``/drive/command``
(reference, command, error, controller compute time, solver path), ``/drive/feedback`` (what
the drive reported) and ``/mpc/prediction``; faults and fallbacks go to ``/events``.

KPIs (:mod:`hil.servo.tracking`, the ``--json`` document): the tracking error after
``settle_s``, the controller's step time, and ``deadline_misses``, which counts, in real
time, ticks the loop skipped plus ticks whose command left after the next tick's deadline
(always 0 in lockstep, where slow compute costs no virtual time).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from typing import Any, cast

from hil.controllers.base import (
    CountsFallbacks,
    ServoController,
    horizons_of,
    position_input_of,
    solver_of,
)
from hil.controllers.servo.references import PlacedReference, Reference, Scenario, parse_scenario
from hil.core.clock import Clock, RealtimeClock, SimClock
from hil.core.loop import FixedRateLoop
from hil.core.notice import warn
from hil.core.plugins import (
    build_controller,
    controller_factory,
    controller_short_name,
)
from hil.core.registry import scheme_of
from hil.core.run import (
    EventBuffer,
    Experiment,
    RunPlan,
    RunResult,
    controller_budget,
    default_session_path,
    run_experiment,
)
from hil.core.session import Session
from hil.core.settings import settings_json
from hil.core.verdict import SignalWatch, split_limits
from hil.drivers.canopen import CanDriveMaster, SdoAbortError
from hil.errors import HilError, SafetyStopError, UsageError
from hil.servo.builtin import ServoContext
from hil.servo.config import EMULATED
from hil.servo.options import ServoRunOptions
from hil.servo.rig import open_drive, share_lockstep_time
from hil.servo.safety import SafetyMonitor
from hil.servo.settings import check_controller_period, resolve_servo
from hil.servo.task import (
    DISTURBANCE_OBJECT,
    ServoTask,
)
from hil.servo.tracking import reference_amplitude

# a step longer than this stops the run: far beyond any real controller's step (the MPC takes
# ~50 us), and long enough that a stall of the machine (a collector pass, a preempted VM) does
# not pass for a hung controller; the loop counts the ticks a slow step costs in real time
STEP_BUDGET_S = 0.25
# per-tick signals a --limit may name (magnitudes, except the position)
SIGNALS = ("abs_error_deg", "abs_command_mA", "abs_velocity_deg_s", "position_deg")

#: the KPIs of ``hil servo run`` a limit may name (groups by their name)
KPI_NAMES = ("max_error_deg", "max_error_pct", "rms_error_deg", "cumulative_error_deg",
             "step_us", "peak_current_mA", "peak_requested_mA", "deadline_misses", "ticks",
             "stale_feedback", "clamped_commands", "wall_s", "realtime_factor", "solver_paths",
             "empc_fallbacks", "faults")

def make_controller(options: ServoRunOptions, scenario: Scenario, session: Any = None,
                    params: Mapping[str, Any] | None = None,
                    factory: Callable[..., Any] | None = None,
                    umax_ma: float | None = None, *,
                    reference: Reference | None = None,
                    period_s: float | None = None) -> ServoController:
    """The controller of the run, built from its spec as ``factory(reference, params)``
    (``context=`` too when the factory takes it); ``factory``: already loaded and checked;
    ``umax_ma``: its current bound (default: the run's, as :func:`resolve_servo` gives it);
    ``reference``: the run's (placed where the axis starts), else the scenario's;
    ``period_s``: the cycle period it is stepped at (default: the run's). A
    ``position_input`` other than wrapped or unwrapped is a ConfigError naming it."""
    if umax_ma is None or period_s is None:
        settings = resolve_servo(options)
        umax_ma = settings.umax_ma if umax_ma is None else umax_ma
        period_s = settings.drive.master.cycle_period_s if period_s is None else period_s
    context = ServoContext(options.ht, options.hu, options.hp, options.ert, umax_ma, session,
                           period_s)
    values = dict(options.params if params is None else params)
    label = options.label
    if factory is None:
        factory, label = controller_factory(options.controller, scenario.reference, values,
                                            method="step", application="servo")
    controller = build_controller(factory, label, scenario.reference if reference is None
                                  else reference, values, method="step",
                                  application="servo", context=context)
    position_input_of(controller, label)
    return cast(ServoController, controller)


def run_servo(options: ServoRunOptions,
              on_started: Callable[[CanDriveMaster], None] | None = None) -> RunResult:
    """Run one servo session on one axis; ``on_started(master)`` is called once the drive is
    enabled. (:func:`hil.servo.axes_run.run_any`, what ``hil servo run`` and
    :func:`hil.api.run_servo` call, runs several axes too.)

    Drive errors (fault, link lost) stop the loop; the drive is put in its safe state, the
    session file is finished with the KPIs so far, and the error is raised with its path."""
    if options.axes or resolve_servo(options).drive.axes:
        raise UsageError("several axes (--axes or [[axis]]) run through "
                         "hil.servo.axes_run.run_any (as hil servo run and hil.api.run_servo "
                         "do), not run_servo")
    return run_experiment(ServoExperiment(options, on_started))


class ServoExperiment(Experiment):
    """``hil servo run`` as the run pipeline drives it."""

    kpi_names: tuple[str, ...] = KPI_NAMES  # what a --limit may name

    def __init__(self, options: ServoRunOptions,
                 on_started: Callable[[CanDriveMaster], None] | None = None) -> None:
        self.options = options
        self.on_started = on_started
        self.master: CanDriveMaster | None = None
        self.task: ServoTask | None = None
        self.umax_ma: float | None = None  # the controller's bound, once the drive is open

    def parse_reference(self) -> Scenario:
        """The run's scenario, from ``--reference``."""
        return parse_scenario(self.options.reference)

    def plan(self) -> RunPlan:
        options = self.options
        self.scenario = self.parse_reference()
        self.settings = resolve_servo(options)
        self.drive = drive = self.settings.drive
        self.drive_url = self.settings.drive_url
        self.params = {**drive.run.params, **options.params}
        # checked before anything is opened: a spec that cannot load leaves no file behind
        self.factory, _ = controller_factory(options.controller, self.scenario.reference,
                                             self.params, method="step", application="servo")
        check_controller_period(self.factory, options.label, drive)
        self.period_s = drive.master.cycle_period_s
        kpi_limits, signal_limits = split_limits([*drive.run.limits, *options.limits],
                                                 SIGNALS, self.kpi_names)
        self.watch = SignalWatch(signal_limits)
        self.out = options.out or default_session_path(
            "servo", controller_short_name(options.label))
        run_info = options.record() | {
            "controller": options.label, "params": self.params,
            "limits": [str(lim) for lim in (*kpi_limits, *signal_limits)]}
        return RunPlan(
            kind="servo", label=options.label, session_path=self.out,
            clock=RealtimeClock() if options.realtime else SimClock(),
            base_period_s=self.period_s, duration_s=options.duration_s,
            kpi_limits=tuple(kpi_limits), watch=self.watch,
            config={"servo": run_info, "drive": drive.data,
                    "settings": settings_json(self.settings.settings())},
            config_text=drive.text,
            config_name="drive.toml", recording=options.recording,
            devices=self._devices(), quiet=options.quiet)

    def _devices(self) -> tuple[tuple[str, str], ...]:
        """The drive's bus, locked for the run (an emulated drive is the run's own, and
        python-can's ``virtual`` bus lives inside one process)."""
        url = self.drive_url
        return () if scheme_of(url) in (EMULATED, "virtual") else (("drive bus", url),)

    def open_devices(self, clock: Clock, on_event: EventBuffer) -> None:
        """The drive master, its bus reached and the drive in a known state (not enabled)."""
        options = self.options
        for kind, message in self.settings.notices:
            warn(message)
            on_event(kind, message, level="warning", source="settings")
        master = open_drive(self.drive_url, self.drive, on_event=on_event,
                            realtime=options.realtime, can_log=options.can_log)
        try:
            if self.drive.master.lockstep:  # over a bus: one clock on both sides of the wire
                share_lockstep_time(master, on_event)
            if options.reset_fault:
                master.fault_reset()
            master.open()
        except BaseException:
            master.close()
            raise
        self.master = master

    def build_controller(self, session: Session) -> None:
        """The controller, built with the run's reference: placed where the axis stands when
        the drive is enabled (the servo task places it, before the first step)."""
        self.reference = PlacedReference(self.scenario.reference,
                                         relative=self.options.from_here)
        assert self.master is not None
        self.umax_ma = min(self.settings.umax_ma, self.master.current_limit_ma)
        self.controller = make_controller(self.options, self.scenario, session, self.params,
                                          self.factory, self.umax_ma, reference=self.reference,
                                          period_s=self.period_s)

    def start(self, session: Session) -> None:
        master, options = self.master, self.options
        assert master is not None
        master.configure()
        session.recorder.metadata("drive", {"json": json.dumps(master.describe())})
        master.enable()
        session.add_component(master)
        if self.scenario.disturbance is not None:
            check_disturbance_object(master)
        self.task = ServoTask(
            session, master, self.controller, self.scenario, reference=self.reference,
            label=options.label,
            settle_s=options.settle_s, prediction_every=options.prediction_period,
            budget_s=controller_budget(options.controller_budget_s, options.realtime,
                                       STEP_BUDGET_S),
            safety=SafetyMonitor(self.drive.safety, self.period_s), watch=self.watch)
        session.add_task(self.task)
        if self.on_started is not None:
            self.on_started(master)

    def finish(self, session: Session) -> None:
        """A safety stop ends the run as an error (the drive is already in its safe state)."""
        if self.task is not None and self.task.safety.stopped is not None:
            raise SafetyStopError(self.task.safety.stopped)

    def close_devices(self) -> None:
        if self.master is not None:
            self.master.close()

    def kpis(self, session: Session, wall_s: float, error: HilError | None) -> dict[str, Any]:
        """The ``--json`` document: the keys the README documents first, then context."""
        options, task, master = self.options, self.task, self.master
        assert master is not None
        base: dict[str, Any] = {"controller": options.label}
        if task is not None:
            tracking = task.stats.kpis(reference_amplitude(self.scenario))
        else:
            tracking = {"max_error_deg": None, "max_error_pct": None, "rms_error_deg": None,
                        "cumulative_error_deg": None,
                        "step_us": {"median": 0.0, "p99": 0.0, "max": 0.0},
                        "peak_current_mA": None, "peak_requested_mA": None}
        peak = tracking.pop("peak_current_mA")
        requested = tracking.pop("peak_requested_mA")
        base.update(tracking)
        loop = session.loop
        ticks = task.stats.ticks if task is not None else 0
        base["deadline_misses"] = (loop.skipped_ticks + task.late_writes
                                   if task is not None and options.realtime else 0)
        base["ticks"] = ticks
        base["cycle_period_us"] = round(self.period_s * 1e6)
        base["mcap"] = options.recording.first_file(self.out)
        base.update({
            "reference": options.reference,
            "drive": master.url,
            "clock": session.clock.mode,
            "umax_mA": self.umax_ma if self.umax_ma is not None else self.settings.umax_ma,
            "current_limit_mA": master.current_limit_ma,  # the smallest of the chain
            "settle_s": options.settle_s,
            "peak_current_mA": peak,          # sent to the drive, after the clamp
            "peak_requested_mA": requested,   # the controller's request
            "stale_feedback": task.stale if task is not None else 0,
            "clamped_commands": master.stats.clamped_commands,
            "wall_s": round(wall_s, 4),
            "realtime_factor": realtime_factor(ticks, loop),
            "stop_reason": loop.stop_reason,
        })
        controller = task.controller if task is not None else None
        horizons = horizons_of(controller)
        if horizons is not None:
            base.update({"ert": horizons.ert, "ht": horizons.ht, "hu": horizons.hu,
                         "hp": horizons.hp})
            solver = solver_of(controller)
            if solver is not None:
                base["solver_paths"] = dict(solver.counts)
            if isinstance(controller, CountsFallbacks):
                base["empc_fallbacks"] = int(controller.fallbacks)
        faults = {"stale_feedback": base["stale_feedback"],
                  "late_frames": master.stats.late_frames, "emcy": master.stats.emcy}
        base["faults"] = faults
        base["disturbed"] = bool(faults["stale_feedback"] or faults["emcy"])
        return base


def realtime_factor(ticks: int, loop: FixedRateLoop) -> float | None:
    """Simulated time over the wall time the loop spent ticking (the writer's start and the
    safe stop are not the loop's pace); None before a tick."""
    if loop.ticking_s <= 0:
        return None
    return round(ticks * (loop.base_period_ns / 1e9) / loop.ticking_s, 2)


def check_disturbance_object(master: CanDriveMaster) -> None:
    """The disturbance scenario pushes the axis through the emulated drive's 0x2003."""
    try:
        master.sdo.write(DISTURBANCE_OBJECT, 0, 0, "<h")
    except SdoAbortError as exc:
        raise UsageError(
            "the disturbance scenario needs the emulated drive's disturbance torque object "
            f"0x2003 (a test hook), which this drive refuses: {exc}") from None
