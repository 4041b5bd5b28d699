"""The drive moving the axis on its own: ``hil drive move`` (a profile position move, PP) and
``hil drive home`` (a homing, HM), each a run of the pipeline (:mod:`hil.core.run`) like a
servo run - the same drive URLs, lockstep or ``--realtime``, the bus lock, the session, the
safe stop - whose loop task cycles the drive through the move or the homing
(:mod:`hil.drivers.canopen.motion`) and ends with it; and the homing of ``hil servo run
--home`` before its own cycles.

Recorded: ``/drive/feedback`` every cycle (the profile as the drive ran it: position,
velocity, current, statusword), ``/drive/motion`` (what each cycle sent: the target and the
mode's controlword bits), the profile or homing objects as the drive holds them (metadata
``motion``), events ``drive.motion``. The KPIs (:class:`MotionKpis`): where it ended, how long
it took, the peak velocity and current. hil's ``[safety]`` position range and speed hold too;
the following error is the drive's (PP: statusword bit 13), there being no hil reference.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from hil.core.clock import Clock, RealtimeClock, SimClock
from hil.core.kpis import Kpis, kpi
from hil.core.loop import Task
from hil.core.recording.recording_options import RecordingOptions
from hil.core.registry import scheme_of
from hil.core.run import (
    EventBuffer,
    Experiment,
    RunPlan,
    RunResult,
    default_session_path,
    run_experiment,
)
from hil.core.session import Session
from hil.core.settings import settings_json
from hil.core.verdict import SignalWatch
from hil.drivers.canopen import CanDriveMaster, Feedback
from hil.drivers.canopen.motion import (
    Homing,
    Motion,
    MotionError,
    PositionMove,
    homing,
    run_motion,
    timed_out,
)
from hil.drivers.canopen.profile import profile_writes
from hil.errors import SafetyStopError, UsageError
from hil.protocols.cia402 import CW_ENABLE_OPERATION, HOMING_METHOD, PROFILE_OBJECTS
from hil.servo.config import EMULATED, DriveConfig
from hil.servo.drives import RunDrives
from hil.servo.options import ServoRunOptions
from hil.servo.rig import keep_lockstep_time, lone_axis, open_drives, reach, tell_notices
from hil.servo.safety import ServoSafety
from hil.servo.settings import lockstep_over_a_bus, resolve_servo
from hil.servo.topics import FEEDBACK_SCHEMA

#: the two motions and the mode each runs in
MOTIONS = {"move": "pp", "home": "hm"}
#: what a motion's own settings set (``hil drive move --velocity``, ``hil.api.move_drive(
#: velocity_deg_s=)``): name -> the key of drive.toml
MOTION_KEYS = {"velocity_deg_s": "profile.velocity_deg_s",
               "acceleration_deg_s2": "profile.acceleration_deg_s2",
               "deceleration_deg_s2": "profile.deceleration_deg_s2",
               "method": "homing.method", "offset_deg": "homing.offset_deg",
               "switch_speed_deg_s": "homing.switch_speed_deg_s",
               "zero_speed_deg_s": "homing.zero_speed_deg_s",
               "homing_acceleration_deg_s2": "homing.acceleration_deg_s2"}
MOTION_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.DriveMotion",
    "description": "What one cycle of a move or a homing sent the drive.",
    "properties": {
        "t_s": {"type": "number", "description": "since the drive was enabled [s]"},
        "target_deg": {"type": "number", "description": "a move's target (multi-turn)"},
        "controlword": {"type": "integer", "x-cdr": "uint16"},
    },
}


@dataclass(frozen=True)
class MotionOptions:
    """``hil drive move`` (``motion = "move"``: to ``target_deg``, or by it with
    ``relative``) and ``hil drive home``. ``keys``: the ``[profile]`` and ``[homing]`` keys
    their flags set, each with its flag (``{"profile.velocity_deg_s": (90.0,
    "--velocity")}``); the rest as ``hil servo run``'s."""

    motion: str
    target_deg: float | None = None
    relative: bool = False
    keys: Mapping[str, tuple[float, str]] = field(default_factory=dict)
    drive: str | None = None
    node: int | None = None
    drive_config: str | None = None
    eds: str | None = None
    realtime: bool = False
    out: str | None = None
    quiet: bool = False
    reset_fault: bool = False
    can_log: str | None = None
    recording: RecordingOptions = field(default_factory=RecordingOptions)

    def __post_init__(self) -> None:
        if self.motion not in MOTIONS:
            raise UsageError(f"a motion is {' or '.join(MOTIONS)}, got {self.motion!r}")
        if (self.motion == "move") != (self.target_deg is not None):
            raise UsageError("a move has a target, a homing none")
        if self.target_deg is not None and not math.isfinite(self.target_deg):
            raise UsageError(f"the target must be a finite angle [deg], got {self.target_deg}")

    def servo(self) -> ServoRunOptions:
        """As a servo run's options: the drive, its config and the session."""
        return ServoRunOptions(controller="", drive=self.drive, node=self.node,
                               drive_config=self.drive_config, eds=self.eds,
                               realtime=self.realtime, out=self.out, quiet=self.quiet,
                               reset_fault=self.reset_fault, can_log=self.can_log,
                               recording=self.recording)

    def record(self) -> dict[str, Any]:
        info = asdict(self)
        info["keys"] = {key: value for key, (value, _) in self.keys.items()}
        return info


@dataclass(frozen=True, kw_only=True)
class MotionPlan(RunPlan):
    """A move or a homing, decided: the drive config with the motion's mode and flags laid
    in, and where the drive is."""

    drive: DriveConfig
    drive_url: str


def motion_drive(options: MotionOptions) -> tuple[DriveConfig, str, list[Any]]:
    """The drive config of ``options``' motion (its mode, its flags' keys each under its
    flag's name), the drive's URL and every setting with its origin."""
    settings = resolve_servo(options.servo())
    drive = settings.drive
    for key, (value, flag) in options.keys.items():
        table, _, name = key.partition(".")
        drive = drive.laid_over({table: {name: value}}, flag)
    drive = drive.laid_over({"master": {"mode": MOTIONS[options.motion]}},
                            f"hil drive {options.motion}")
    if settings.drive.master.lockstep:  # laid over again: a key is no lockstep
        drive = lockstep_over_a_bus(drive)
    return drive, settings.drive_url, drive.settings()


def plan_motion(options: MotionOptions) -> MotionPlan:
    drive, url, settings = motion_drive(options)
    profile = drive.master.profile
    timeout = profile.move_timeout_s if options.motion == "move" else profile.homing_timeout_s
    out = options.out or default_session_path("motion", options.motion)
    return MotionPlan(
        kind="motion", session_path=out, label=options.motion,
        clock=RealtimeClock() if options.realtime else SimClock(),
        base_period_s=drive.master.cycle_period_s, duration_s=timeout, kpi_limits=(),
        watch=SignalWatch([]),
        config={"motion": options.record(), "drive": drive.data,
                "settings": settings_json(settings)},
        config_text=drive.text, config_name="drive.toml", recording=options.recording,
        devices=() if scheme_of(url) in (EMULATED, "virtual") else (("drive bus", url),),
        quiet=options.quiet, drive=drive, drive_url=url)


def run_motion_options(options: MotionOptions) -> RunResult:
    """``hil drive move`` / ``hil drive home``: the run and its result."""
    return run_experiment(MotionExperiment(options))


@dataclass
class MotionKpis(Kpis):
    """A move's or a homing's ``--json`` document."""

    motion: str = kpi("", limit=False)
    reached: bool = kpi(False)          # at its target (bit 10), or home attained (bit 12)
    target_deg: float | None = kpi(optional=True)
    method: int | None = kpi(limit=False, optional=True)
    position_deg: float | None = kpi()  # where the axis ended
    error_deg: float | None = kpi(optional=True)  # a move's: position - target
    time_s: float | None = kpi()        # to the end of the move or the homing
    peak_velocity_deg_s: float = kpi(0.0)
    peak_current_ma: float | None = kpi(0.0, key="peak_current_mA")  # None: not measured
    ticks: int = kpi(0)
    cycle_period_us: int = kpi(0, limit=False)
    drive: str = kpi("", limit=False)
    clock: str = kpi("", limit=False)
    mcap: str = kpi("", limit=False)
    wall_s: float = kpi(0.0)
    stop_reason: str | None = kpi(limit=False)


class MotionTask(Task):
    """read feedback -> the motion's next cycle -> write it -> record; the loop stops once
    the motion is done, or hil's safety limits are crossed."""

    def __init__(self, session: Session, master: CanDriveMaster, motion: Motion,
                 safety: ServoSafety, target_deg: float | None) -> None:
        super().__init__("motion")
        self.session, self.master, self.motion = session, master, motion
        self.safety, self.target_deg = safety, target_deg
        self.period_s = session.loop.base_period_ns / 1e9
        self.feedbacks = session.topic("/drive/feedback", FEEDBACK_SCHEMA, high_rate=True)
        self.sent = session.topic("/drive/motion", MOTION_SCHEMA, high_rate=True)
        self.ticks = 0
        self.end_s: float | None = None  # when the motion was done [s]
        self.peak_velocity = 0.0
        self.peak_current: float | None = 0.0
        self.stopped: str | None = None
        self._feedback: Feedback | None = None
        self._next = (0.0, 0)

    @property
    def feedback(self) -> Feedback | None:
        """The drive's last feedback (None before the first tick)."""
        return self._feedback

    def read(self, t_ns: int) -> None:
        self._feedback = self.master.receive_feedback()

    def compute(self, t_ns: int) -> None:
        assert self._feedback is not None
        self._next = self.motion.next(self._feedback)
        if self.motion.done and self.end_s is None:
            self.end_s = self.ticks * self.period_s
            self.session.loop.stop("done")

    def write(self, t_ns: int) -> None:
        self.master.send_set_point(*self._next)

    def record(self, t_ns: int) -> None:
        feedback = self._feedback
        assert feedback is not None
        self.feedbacks.log(t_ns, (feedback.position_deg, feedback.velocity_deg_s,
                                  feedback.current_ma, None, feedback.statusword,
                                  feedback.cycle, feedback.fresh, feedback.rtt_us))
        self.sent.log(t_ns, (self.ticks * self.period_s, self.target_deg,
                             self._next[1] | CW_ENABLE_OPERATION))
        self.peak_velocity = max(self.peak_velocity, abs(feedback.velocity_deg_s))
        current = feedback.current_ma
        if not math.isfinite(current):  # a drive without 0x6077: its current is not measured
            self.peak_current = None
        elif self.peak_current is not None:
            self.peak_current = max(self.peak_current, abs(current))
        self.ticks += 1
        stop = self._unsafe(feedback)
        if stop is not None:
            self.stopped = stop
            self.session.event("safety.stop", stop, level="error", source="safety")
            self.session.loop.stop(stop)

    def _unsafe(self, feedback: Feedback) -> str | None:
        """hil's [safety] position range and speed (the drive keeps its own following
        error)."""
        s = self.safety
        if not s.enabled:
            return None
        if not s.position_min_deg <= feedback.position_deg <= s.position_max_deg:
            return (f"position {feedback.position_deg:.3f} deg outside [{s.position_min_deg:g}, "
                    f"{s.position_max_deg:g}] deg ([safety] position range)")
        if abs(feedback.velocity_deg_s) > s.velocity_max_deg_s:
            return (f"velocity {feedback.velocity_deg_s:.1f} deg/s beyond "
                    f"{s.velocity_max_deg_s:g} deg/s ([safety] velocity_max_deg_s)")
        return None


class MotionExperiment(Experiment[MotionPlan]):
    """``hil drive move`` and ``hil drive home`` as the run pipeline drives them."""

    def __init__(self, options: MotionOptions) -> None:
        self.options = options
        self.drives = RunDrives()
        self.task: MotionTask | None = None
        self.method: int | None = None  # a homing's

    def plan(self) -> MotionPlan:
        return plan_motion(self.options)

    @property
    def master(self) -> CanDriveMaster:
        return self.drives.masters[0]

    def open_devices(self, clock: Clock, on_event: EventBuffer) -> None:
        plan = self.planned
        try:
            self.drives.add(open_drives(plan.drive_url, plan.drive, [lone_axis(plan.drive)],
                                        on_event=on_event, realtime=self.options.realtime,
                                        can_log=self.options.can_log))
            reach(self.master, on_event, self.options.reset_fault)
            # what configure would refuse, refused before there is a session
            profile_writes(self.master.objects, self.master.operation,
                           self.master.config.profile, self.master.scaling)
            self.method = homing_method(self.master) if self.options.motion == "home" \
                else None
        except BaseException:
            self.close_devices()
            raise

    def build_controller(self, session: Session) -> None:
        """A motion has no controller: the drive moves the axis."""

    def start(self, session: Session) -> None:
        master, options = self.master, self.options
        master.configure()
        tell_notices(master)
        session.recorder.metadata("drive", {"json": json.dumps(master.describe())})
        session.recorder.metadata("motion", {"json": json.dumps(profile_held(master))})
        master.enable()
        keep_lockstep_time(master, session.event)
        session.add_component(self.drives)
        motion: Motion
        target = None
        if options.target_deg is None:
            assert self.method is not None
            motion = homing(master, self.method)
        else:  # a relative target from where the axis was enabled
            assert master.feedback is not None
            target = options.target_deg + (master.feedback.position_deg if options.relative
                                           else 0.0)
            motion = PositionMove(target)
        session.event("drive.motion", f"drive node {master.node_id}: {motion.what}",
                      source=f"drive{master.node_id}", target_deg=target)
        self.task = MotionTask(session, master, motion, self.planned.drive.safety, target)
        session.add_task(self.task)

    def finish(self, session: Session) -> None:
        task = self.task
        assert task is not None
        feedback = task.feedback
        assert feedback is not None
        if task.stopped is not None:
            raise SafetyStopError(task.stopped)
        if not task.motion.done:
            raise timed_out(task.motion, feedback, self.planned.duration_s)
        session.event("drive.motion", f"drive node {self.master.node_id}: {task.motion.what}: "
                      f"done at {feedback.position_deg:.3f} deg in {task.end_s:.3f} s",
                      source=f"drive{self.master.node_id}", position_deg=feedback.position_deg)

    def close_devices(self) -> None:
        drives, self.drives = self.drives, RunDrives()
        drives.close()

    def kpis(self, session: Session, wall_s: float, error: Any) -> MotionKpis:
        task, plan = self.task, self.planned
        feedback = task.feedback if task is not None else None
        target = task.target_deg if task is not None else None
        position = feedback.position_deg if feedback is not None else None
        motion = task.motion if task is not None else None
        return MotionKpis(
            motion=self.options.motion, reached=bool(motion is not None and motion.done),
            target_deg=target,
            method=motion.method if isinstance(motion, Homing) else None,
            position_deg=position,
            error_deg=None if target is None or position is None else position - target,
            time_s=task.end_s if task is not None else None,
            peak_velocity_deg_s=task.peak_velocity if task is not None else 0.0,
            peak_current_ma=task.peak_current if task is not None else 0.0,
            ticks=task.ticks if task is not None else 0,
            cycle_period_us=round(plan.base_period_s * 1e6), drive=plan.drive_url,
            clock=session.clock.mode, mcap=plan.recording.first_file(plan.session_path),
            wall_s=round(wall_s, 4), stop_reason=session.loop.stop_reason)


def homing_method(master: CanDriveMaster) -> int:
    """The homing method of a homing: the configured one (configure writes it to 0x6098),
    else the drive's own; a drive without 0x6098, or with method 0 (none), cannot home."""
    n = master.node_id
    configured = master.config.profile.homing_method
    if not master.objects.has(HOMING_METHOD):
        raise MotionError(f"drive node {n} has no 0x6098 (homing method): it cannot home")
    method = master.objects.read(HOMING_METHOD, 0, "<b") if configured is None else configured
    if not method:
        raise MotionError(f"drive node {n}'s homing method 0x6098 is 0 (none): give --method "
                          "N or [homing] method")
    return method


def profile_held(master: CanDriveMaster) -> dict[str, float | None]:
    """The objects of the master's mode's profile as the drive holds them, in hil's units
    (None: the drive has not got one)."""
    held: dict[str, float | None] = {}
    for index, sub in master.operation.profile:
        shape = PROFILE_OBJECTS[index, sub]
        raw = master.objects.read(index, sub, shape.fmt)
        held[shape.title] = None if raw is None else \
            master.scaling.degrees(raw) if shape.unit else raw
    return held


def home_axis(master: CanDriveMaster, timeout_s: float) -> Feedback:
    """``hil servo run --home``: the drive homed in HM before the run's own mode (its
    [homing] keys written), then stopped (the master switches modes with the drive not
    enabled); the feedback at home, in the drive's new frame."""
    run_mode = master.operation.name
    master.use_mode("hm")
    master.configure()
    tell_notices(master)
    to_home = homing(master, homing_method(master))
    master.enable()
    try:
        at_home = run_motion(master, to_home, timeout_s)
    finally:
        master.safe_state()
        master.use_mode(run_mode)
    return at_home
