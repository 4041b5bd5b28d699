"""The servo scenario (``hil servo run``): a controller closing the loop through the CAN drive
link, as the run pipeline (:mod:`hil.core.run`) drives it.

:class:`ServoExperiment` opens the drive (the emulator in lockstep by default), builds the
controller, enables the drive and runs one :class:`~hil.servo.task.ServoTask` at the base
period T = 500 us (the published axis model's). Recorded per tick: ``/drive/command``
(reference, command, error, controller compute time, solver path), ``/drive/feedback`` (what
the drive reported) and ``/mpc/prediction``; faults and fallbacks go to ``/events``.

KPIs (:mod:`hil.servo.tracking`, the ``--json`` document): the tracking error after
``settle_s``, the controller's step time, and ``deadline_misses``, which counts, in real
time, ticks the loop skipped plus ticks whose command left after the next tick's deadline
(always 0 in lockstep, where slow compute costs no virtual time).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any, cast

from controllers.base import CountsFallbacks, ServoController, horizons_of, solver_of
from controllers.servo.model import SAMPLE_PERIOD_S
from controllers.servo.references import Scenario, parse_scenario
from drivers.canopen import CanDriveMaster, SdoAbortError
from hil.core.clock import Clock, RealtimeClock, SimClock
from hil.core.errors import ConfigError, HilError, SafetyStopError, UsageError
from hil.core.loop import FixedRateLoop
from hil.core.plugins import (
    build_controller,
    controller_factory,
    controller_label,
    controller_short_name,
)
from hil.core.ranges import MAX_MPC_HORIZON, check_at_most, check_duration
from hil.core.recorder import RecordingOptions
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
from hil.core.verdict import Limit, SignalWatch, split_limits
from hil.servo.builtin import ServoContext
from hil.servo.config import EMULATED, DriveConfig, load_drive_config
from hil.servo.defaults import DEFAULT_REFERENCE
from hil.servo.rig import open_drive
from hil.servo.safety import SafetyMonitor
from hil.servo.task import (
    DISTURBANCE_OBJECT,
    PREDICTION_EVERY_REALTIME,
    PREDICTION_EVERY_TICK_UP_TO_S,
    ServoTask,
)
from hil.servo.tracking import reference_amplitude

# a step longer than this stops the run: far beyond any real controller's step (the MPC takes
# ~50 us), and long enough that a stall of the machine (a collector pass, a preempted VM) does
# not pass for a hung controller; the loop counts the ticks a slow step costs in real time
STEP_BUDGET_S = 0.25
# per-tick signals a --limit may name (magnitudes, except the position)
SIGNALS = ("abs_error_deg", "abs_command_mA", "abs_velocity_deg_s", "position_deg")
# lockstep over a real bus: wait this long for the TPDOs (a lockstep run never ends a cycle
# early; a drive that does not answer within it is a lost link)
LOCKSTEP_RX_TIMEOUT_US = 100_000

#: the KPIs of ``hil servo run`` a limit may name (groups by their name)
KPI_NAMES = ("max_error_deg", "max_error_pct", "rms_error_deg", "cumulative_error_deg",
             "step_us", "peak_current_mA", "peak_requested_mA", "deadline_misses", "ticks",
             "stale_feedback", "clamped_commands", "wall_s", "realtime_factor", "solver_paths",
             "empc_fallbacks", "faults")

#: ``hil servo run``'s flags (argparse dests) -> the option they set, where the names differ
FLAG_OPTIONS = {"duration": "duration_s", "config": "drive_config", "settle": "settle_s",
                "limit": "limits", "param": "params", "controller_budget": "controller_budget_s"}


@dataclass(frozen=True)
class ServoRunOptions:
    """Everything a servo run is made of (the flags of ``hil servo run``).

    ``drive_config`` is a drive TOML laid over ``hil/configs/drive.toml``; ``drive_overrides``
    is laid over the result last (after ``umax`` and ``node``), for tests and scripts.
    ``prediction_every`` None means every tick in lockstep, ``PREDICTION_EVERY_REALTIME``
    ticks in real time.
    """

    controller: str | Callable[..., Any]
    params: Mapping[str, Any] = field(default_factory=dict)
    drive: str | None = "emulated"   # a drive URL; None: drive.toml's [bus]
    node: int = 1
    ert: str = "foh"
    ht: int = 8
    hu: int = 8
    hp: int = 50
    umax: float = 1000.0
    reference: str = DEFAULT_REFERENCE
    duration_s: float = 2.0
    realtime: bool = False
    out: str | None = None
    drive_config: str | None = None
    settle_s: float = 0.0
    prediction_every: int | None = None
    drive_overrides: Mapping[str, Any] = field(default_factory=dict)
    limits: tuple[Limit, ...] = ()
    controller_budget_s: float | None = None  # per step; None: STEP_BUDGET_S in real time
    recording: RecordingOptions = field(default_factory=RecordingOptions)
    quiet: bool = False              # no progress line on the terminal
    can_log: str | None = None       # every CAN frame to this file (python-can's formats)
    reset_fault: bool = False        # clear a drive FAULT (CiA 402 fault reset) before enabling
    axes: str | None = None          # NAME=NODE,...: several axes (else drive.toml's [[axis]])

    def __post_init__(self) -> None:
        if not (isinstance(self.umax, (int, float)) and math.isfinite(self.umax)
                and self.umax > 0):
            raise UsageError(f"--umax must be a positive finite number, got {self.umax!r}")
        check_duration(self.duration_s, "--duration", SAMPLE_PERIOD_S)
        for flag, horizon in (("--ht", self.ht), ("--hu", self.hu), ("--hp", self.hp)):
            check_at_most(horizon, MAX_MPC_HORIZON, flag, "the MPC's matrices grow with the "
                          "horizon (a step would take far longer than a 500 us period)")
        if not 0 <= self.settle_s < self.duration_s:
            raise UsageError(f"--settle ({self.settle_s:g} s) must be >= 0 and shorter than "
                             f"--duration ({self.duration_s:g} s)")
        if self.prediction_every is not None and self.prediction_every < 1:
            raise UsageError(f"--prediction-every must be >= 1, got {self.prediction_every}")
        if not 1 <= self.node <= 127:
            raise UsageError(f"--node must be a CANopen node id 1..127, got {self.node}")

    @classmethod
    def from_flags(cls, flags: Mapping[str, Any]) -> ServoRunOptions:
        """The options of ``hil servo run``'s flags as a dict (argparse dests; a sweep's swept
        values laid over them); flags that are not run options (``json``, ``junit``...) are
        ignored. The horizons ``ht`` and ``hu`` default to 8, to 3 for ``empc`` (the paper's
        drive)."""
        known = {f.name for f in fields(cls)}
        values: dict[str, Any] = {}
        for flag, value in flags.items():
            name = FLAG_OPTIONS.get(flag, flag)
            if name in known and value is not None:
                values[name] = value
        values["params"] = dict(values.get("params", {}))
        values["limits"] = tuple(values.get("limits", ()))
        safety = dict(flags.get("safety") or [])
        if safety:  # --safety KEY=VALUE: laid over drive.toml's [safety], checked as strictly
            overrides = dict(values.get("drive_overrides", {}))
            overrides["safety"] = {**overrides.get("safety", {}), **safety}
            values["drive_overrides"] = overrides
        default_horizon = 3 if values.get("controller") == "empc" else 8
        for horizon in ("ht", "hu"):
            values.setdefault(horizon, default_horizon)
        return cls(**values)

    @property
    def prediction_period(self) -> int:
        if self.prediction_every is not None:
            return self.prediction_every
        long_run = self.duration_s > PREDICTION_EVERY_TICK_UP_TO_S
        return PREDICTION_EVERY_REALTIME if self.realtime or long_run else 1

    @property
    def label(self) -> str:
        return controller_label(self.controller)

    def describe_controller(self) -> str:
        if self.controller == "pid":
            return "pid (cascaded P/PI + notch, Table I)"
        if self.controller in ("mpc", "empc"):
            return (f"{self.controller} ({self.ert.upper()}, H_t = {self.ht}, H_u = {self.hu}, "
                    f"H_p = {self.hp})")
        return self.label

    def record(self) -> dict[str, Any]:
        """The options as the session's ``servo`` metadata records them."""
        info = asdict(self)
        for name in ("drive_overrides", "limits", "controller", "params"):
            info.pop(name)
        return info


def make_controller(options: ServoRunOptions, scenario: Scenario, session: Any = None,
                    params: Mapping[str, Any] | None = None,
                    factory: Callable[..., Any] | None = None) -> ServoController:
    """The controller of the run, built from its spec as ``factory(reference, params)``
    (``context=`` too when the factory takes it); ``factory``: already loaded and checked."""
    context = ServoContext(options.ht, options.hu, options.hp, options.ert, options.umax,
                           session)
    values = dict(options.params if params is None else params)
    label = options.label
    if factory is None:
        factory, label = controller_factory(options.controller, scenario.reference, values,
                                            method="step", application="servo")
    return cast(ServoController, build_controller(factory, label, scenario.reference, values,
                                                  method="step", application="servo",
                                                  context=context))


def run_servo(options: ServoRunOptions,
              on_started: Callable[[CanDriveMaster], None] | None = None) -> RunResult:
    """Run one servo session on one axis; ``on_started(master)`` is called once the drive is
    enabled. (:func:`hil.servo.axes_run.run_any`, what ``hil servo run`` and
    :func:`hil.api.run_servo` call, runs several axes too.)

    Drive errors (fault, link lost) stop the loop; the drive is put in its safe state, the
    session file is finished with the KPIs so far, and the error is raised with its path."""
    if options.axes or drive_settings(options).axes:
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

    def parse_reference(self) -> Scenario:
        """The run's scenario, from ``--reference``."""
        return parse_scenario(self.options.reference)

    def plan(self) -> RunPlan:
        options = self.options
        self.scenario = self.parse_reference()
        self.drive = drive = drive_settings(options)
        self.params = {**drive.run.params, **options.params}
        # checked before anything is opened: a spec that cannot load leaves no file behind
        self.factory, _ = controller_factory(options.controller, self.scenario.reference,
                                             self.params, method="step", application="servo")
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
            base_period_s=SAMPLE_PERIOD_S, duration_s=options.duration_s,
            kpi_limits=tuple(kpi_limits), watch=self.watch,
            config={"servo": run_info, "drive": drive.data}, config_text=drive.text,
            config_name="drive.toml", recording=options.recording,
            devices=self._devices(), quiet=options.quiet)

    def _devices(self) -> tuple[tuple[str, str], ...]:
        """The drive's bus, locked for the run (an emulated drive is the run's own, and
        python-can's ``virtual`` bus lives inside one process)."""
        url = self.options.drive or self.drive.bus_url
        return () if scheme_of(url) in (EMULATED, "virtual") else (("drive bus", url),)

    def open_devices(self, clock: Clock, on_event: EventBuffer) -> None:
        """The drive master, its bus reached and the drive in a known state (not enabled)."""
        options = self.options
        master = open_drive(options.drive, self.drive, on_event=on_event,
                            realtime=options.realtime, can_log=options.can_log)
        try:
            if options.reset_fault:
                master.clear_fault()
            master.open()
        except BaseException:
            master.close()
            raise
        self.master = master

    def build_controller(self, session: Session) -> None:
        self.controller = make_controller(self.options, self.scenario, session, self.params,
                                          self.factory)

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
            session, master, self.controller, self.scenario, label=options.label,
            settle_s=options.settle_s, prediction_every=options.prediction_period,
            budget_s=controller_budget(options.controller_budget_s, options.realtime,
                                       STEP_BUDGET_S),
            safety=SafetyMonitor(self.drive.safety, SAMPLE_PERIOD_S), watch=self.watch)
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
        """The ``--json`` document: DESIGN.md's keys first, then context."""
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
        base["mcap"] = options.recording.first_file(self.out)
        base.update({
            "reference": options.reference,
            "drive": master.url,
            "clock": session.clock.mode,
            "umax_mA": options.umax,
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
    return round(ticks * SAMPLE_PERIOD_S / loop.ticking_s, 2)


def drive_settings(options: ServoRunOptions) -> DriveConfig:
    """The drive config of the run: default < ``drive_config`` file < flags < overrides."""
    flags = {"master": {"current_limit_mA": float(options.umax), "node_id": options.node}}
    drive = load_drive_config(options.drive_config, overrides=flags)
    if options.drive_overrides:
        drive = drive.laid_over(options.drive_overrides)
    period_us = round(drive.master.cycle_period_s * 1e6)
    if period_us * 1e-6 != SAMPLE_PERIOD_S:
        raise ConfigError(f"{drive.source}: master.cycle_period_us = {period_us}, but the servo "
                          f"controllers are designed for T = {SAMPLE_PERIOD_S * 1e6:g} us")
    if not options.realtime and (options.drive or drive.bus_url) != EMULATED:
        timeout_us = round(drive.master.rx_timeout_s * 1e6)
        drive = drive.laid_over({"master": {
            "rx_timeout_us": max(timeout_us, LOCKSTEP_RX_TIMEOUT_US)}})
    return drive


def check_disturbance_object(master: CanDriveMaster) -> None:
    """The disturbance scenario pushes the axis through the emulated drive's 0x2003."""
    try:
        master.sdo_write(DISTURBANCE_OBJECT, 0, 0, "<h")
    except SdoAbortError as exc:
        raise UsageError(
            "the disturbance scenario needs the emulated drive's disturbance torque object "
            f"0x2003 (a test hook), which this drive refuses: {exc}") from None
