"""The servo scenario (``hil servo run``): a controller closing the loop through the CAN drive link.

One loop task at the base period T = 500 us (the published axis model's): read the drive's
feedback, step the controller, write the current command. The controller's ``step(y_k)`` gives
u_k; the drive applies u_k on the next SYNC and its TPDOs report y_{k+1}, exactly the offline
simulation's ``x(k+1) = A x(k) + B u(k)``, without an extra delay:

* lockstep (``SimClock``, default): ``read`` returns the feedback the last exchange brought,
  ``write`` is ``master.exchange(u)`` (RPDO + SYNC, then the TPDOs);
* real time (``RealtimeClock``, ``--realtime``): the split form, ``read`` is
  ``master.receive_feedback()`` (the TPDOs of the previous tick's SYNC, which travelled while
  the loop slept) and ``write`` is ``master.send_command(u)``.

The controller's time is the tick's slot on the schedule grid (k T), in real time too: a
skipped tick skips its reference sample. With the emulated drive the plant only moves on SYNC,
so a skipped tick also freezes the plant for one period (a real drive holds its last command).

Recorded per tick: ``/drive/command`` (reference, command, error, controller compute time,
solver path), ``/drive/feedback`` (what the drive reported) and ``/mpc/prediction`` (the
predicted inputs û(0..H_u-1|k) and outputs ŷ(1..H_p|k), for waterfall plots). The loop only
queues them (the writer process encodes); in lockstep runs up to
``PREDICTION_EVERY_TICK_UP_TO_S`` the prediction is recorded every tick, otherwise every
``PREDICTION_EVERY_REALTIME``-th tick by default (200 Hz). Faults and fallbacks go to
``/events``.

KPIs (``session.close(kpis=...)`` and the ``--json`` document) are taken over the ticks from
``settle_s`` on: the error is position - reference wrapped to ±180 deg; ``max_error_pct`` is
relative to the sine's amplitude or the trapezoid's stroke (None for a hold); ``step_us`` is
the controller's compute time (Kalman + MPC, or PID) per tick; ``deadline_misses`` counts, in
real time, ticks the loop skipped plus ticks whose command left after the next tick's deadline
(always 0 in lockstep, where slow compute costs no virtual time).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol, cast, runtime_checkable

import numpy as np

from controllers.base import ServoController
from controllers.servo.empc import ExplicitMpc
from controllers.servo.model import SAMPLE_PERIOD_S
from controllers.servo.mpc import TrajectoryMpc
from controllers.servo.references import (
    Reference,
    Scenario,
    Sine,
    Trapezoid,
    parse_scenario,
    wrap180,
)
from drivers.can_drive import CanDriveMaster, Feedback, SdoAbortError
from hil.core.clock import RealtimeClock, SimClock
from hil.core.errors import ConfigError, ControllerError, HilError, UsageError
from hil.core.guard import guarded_call
from hil.core.loop import Task
from hil.core.plugins import (
    build_controller,
    controller_factory,
    controller_label,
    controller_short_name,
)
from hil.core.recorder import RecordingOptions
from hil.core.session import Session
from hil.core.stats import TimingHistogram
from hil.core.verdict import Limit, SignalWatch, split_limits, verdict
from hil.servo.builtin import ServoContext
from hil.servo.config import DriveConfig, load_drive_config
from hil.servo.rig import open_drive

# a step longer than this stops the run: far beyond any real controller's step (the MPC takes
# ~50 us), and long enough that a stall of the machine (a collector pass, a preempted VM) does
# not pass for a hung controller; the loop counts the ticks a slow step costs in real time
STEP_BUDGET_S = 0.25
# per-tick signals a --limit may name (magnitudes, except the position)
SIGNALS = ("abs_error_deg", "abs_command_mA", "abs_velocity_deg_s", "position_deg")
PREDICTION_EVERY_REALTIME = 10  # 200 Hz of /mpc/prediction in real time and in long runs
PREDICTION_EVERY_TICK_UP_TO_S = 60.0  # lockstep runs up to this long record it every tick
LOCKSTEP_RX_TIMEOUT_US = 100_000  # lockstep over a real bus: wait for the TPDOs, no deadline
DISTURBANCE_OBJECT = 0x2003  # the emulated drive's external disturbance torque [mA], INTEGER16

COMMAND_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.ServoCommand",
    "description": "One controller tick: reference r(k), error y(k) - r(k) (wrapped to ±180 "
                   "deg), commanded current u(k), controller compute time.",
    "properties": {
        "t_s": {"type": "number", "description": "tick time on the schedule grid [s]"},
        "reference_deg": {"type": "number"},
        "error_deg": {"type": "number", "x-cdr": "float32"},
        "command_mA": {"type": "number", "x-cdr": "float32",
                       "description": "controller output, before the driver's clamp"},
        "disturbance_mA": {"type": "number", "x-cdr": "float32", "description": "scenario "
                           "disturbance torque injected this tick (0x2003)"},
        "compute_us": {"type": "number", "x-cdr": "float32",
                       "description": "controller step time"},
        "path": {"type": "string", "description": "MPC solver path: unconstrained, qp, "
                 "explicit or fallback"},
    },
}
FEEDBACK_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.DriveFeedback",
    "description": "What the drive reported for tick k (TPDO1 + TPDO2 of the previous SYNC).",
    "properties": {
        "position_deg": {"type": "number", "description": "multi-turn, unwrapped by the master"},
        "velocity_deg_s": {"type": "number", "x-cdr": "float32"},
        "current_mA": {"type": "number", "x-cdr": "float32",
                       "description": "torque actual (0x6077) as current"},
        "command_mA": {"type": "number", "x-cdr": "float32", "description": "current "
                       "commanded on the wire in the cycle that produced this feedback (after "
                       "the driver's clamp)"},
        "statusword": {"type": "integer", "x-cdr": "uint16"},
        "cycle": {"type": "integer", "x-cdr": "uint32"},
        "fresh": {"type": "boolean", "description": "false: the TPDOs were late, values repeat"},
        "rtt_us": {"type": "number", "x-cdr": "float32",
                   "description": "SYNC sent -> both TPDOs received"},
    },
}
PREDICTION_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.MpcPrediction",
    "description": "The MPC's predicted inputs u(k+i|k), i = 0..H_u-1 (held after), and outputs "
                   "y(k+i|k), i = 1..H_p, one sample period apart (continuous angle frame).",
    "properties": {
        "t_s": {"type": "number"},
        "u_mA": {"type": "array", "items": {"type": "number", "x-cdr": "float32"}},
        "y_deg": {"type": "array", "items": {"type": "number", "x-cdr": "float32"}},
    },
}


@dataclass(frozen=True)
class ServoRunConfig:
    """Everything a servo run is made of (the flags of ``hil servo run``).

    ``drive_config`` is a drive TOML laid over ``hil/configs/drive.toml``; ``drive_overrides``
    is laid over the result last (after ``umax`` and ``node``), for tests and scripts.
    ``prediction_every`` None means every tick in lockstep, ``PREDICTION_EVERY_REALTIME``
    ticks in real time.
    """

    controller: str | Callable[..., Any]
    params: dict[str, Any] = field(default_factory=dict)
    drive: str = "emulated"
    node: int = 1
    ert: str = "foh"
    ht: int = 8
    hu: int = 8
    hp: int = 50
    umax: float = 1000.0
    reference: str = "sine:amplitude=2,frequency=10"
    duration_s: float = 2.0
    realtime: bool = False
    out: str | None = None
    drive_config: str | None = None
    settle_s: float = 0.0
    prediction_every: int | None = None
    drive_overrides: dict[str, Any] = field(default_factory=dict)
    limits: tuple[Limit, ...] = ()
    controller_budget_s: float | None = None  # per step; None: STEP_BUDGET_S in real time
    recording: RecordingOptions = field(default_factory=RecordingOptions)

    def __post_init__(self) -> None:
        for name, flag in (("umax", "--umax"), ("duration_s", "--duration")):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise UsageError(f"{flag} must be a positive finite number, got {value!r}")
        if not 0 <= self.settle_s < self.duration_s:
            raise UsageError(f"--settle ({self.settle_s:g} s) must be >= 0 and shorter than "
                             f"--duration ({self.duration_s:g} s)")
        if self.prediction_every is not None and self.prediction_every < 1:
            raise UsageError(f"--prediction-every must be >= 1, got {self.prediction_every}")
        if not 1 <= self.node <= 127:
            raise UsageError(f"--node must be a CANopen node id 1..127, got {self.node}")

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


@dataclass
class ServoRunResult:
    """KPIs (the ``--json`` document), loop timing per task and the path of the session."""

    kpis: dict[str, Any]
    loop: dict[str, Any]
    path: str


# ------------------------------------------------------------------------------- controller
def reference_amplitude(scenario: Scenario) -> float | None:
    """What ``max_error_pct`` is relative to: a sine's amplitude, a trapezoid's stroke."""
    ref = scenario.reference
    if isinstance(ref, Sine):
        return abs(ref.amplitude) or None
    if isinstance(ref, Trapezoid):
        return ref.stroke
    return None


@runtime_checkable
class Predicting(Protocol):
    """A controller that tells its predicted inputs and outputs (the MPCs), recorded to
    ``/mpc/prediction``."""

    def prediction(self) -> tuple[np.ndarray, np.ndarray]: ...


def make_controller(config: ServoRunConfig, scenario: Scenario, session: Any = None,
                    params: Mapping[str, Any] | None = None,
                    factory: Callable[..., Any] | None = None) -> ServoController:
    """The controller of the run, built from its spec as ``factory(reference, params)``
    (``context=`` too when the factory takes it); ``factory``: already loaded and checked."""
    context = ServoContext(config.ht, config.hu, config.hp, config.ert, config.umax, session)
    values = dict(config.params if params is None else params)
    label = config.label
    if factory is None:
        factory, label = controller_factory(config.controller, scenario.reference, values,
                                            method="step", application="servo")
    return cast(ServoController, build_controller(factory, label, scenario.reference, values,
                                                  method="step", application="servo",
                                                  context=context))


# ------------------------------------------------------------------------------- KPIs
class ReferenceSamples:
    """r(k T) for tick k, computed a block of ticks at a time (vectorised, constant memory)."""

    def __init__(self, reference: Reference, dt: float, block: int = 2048) -> None:
        self.reference, self.dt, self.block = reference, dt, block
        self._first = -1
        self._values = np.empty(0)

    def __call__(self, tick: int) -> float:
        first = tick - tick % self.block
        if first != self._first:
            ticks = first + np.arange(self.block)
            self._values = np.asarray(self.reference.position(ticks * self.dt), dtype=float)
            self._first = first
        return float(self._values[tick - first])


class TrackingStats:
    """The run's KPIs, accumulated tick by tick in constant memory: error and current over the
    ticks from ``settle_s`` on (exact running sums and maxima), controller compute time over
    all ticks (a log-bucket histogram: percentiles within 1 %, max exact)."""

    def __init__(self, settle_s: float) -> None:
        self.settle_s = settle_s - 1e-12
        self.ticks = 0
        self.counted = 0
        self.max_error = 0.0
        self.sum_error = 0.0
        self.sum_squares = 0.0
        self.peak_current = 0.0
        self.compute_us = TimingHistogram()

    def add(self, t_s: float, error_deg: float, command_ma: float, compute_us: float) -> None:
        self.ticks += 1
        self.compute_us.add(compute_us)
        if t_s >= self.settle_s:
            e = abs(error_deg)
            self.counted += 1
            self.sum_error += e
            self.sum_squares += e * e
            if e > self.max_error:
                self.max_error = e
            if abs(command_ma) > self.peak_current:
                self.peak_current = abs(command_ma)

    def kpis(self, amplitude: float | None) -> dict[str, Any]:
        if self.counted:
            kpis: dict[str, Any] = {
                "max_error_deg": self.max_error,
                "max_error_pct": 100.0 * self.max_error / amplitude if amplitude else None,
                "rms_error_deg": math.sqrt(self.sum_squares / self.counted),
                "cumulative_error_deg": self.sum_error,
            }
        else:
            kpis = {"max_error_deg": None, "max_error_pct": None, "rms_error_deg": None,
                    "cumulative_error_deg": None}
        step = self.compute_us.summary()
        kpis["step_us"] = {"median": step["p50"], "p99": step["p99"], "max": step["max"]}
        kpis["peak_current_mA"] = self.peak_current if self.counted else None
        return kpis


# ------------------------------------------------------------------------------------ task
class ServoTask(Task):
    """read feedback -> controller step -> write command, then record the tick."""

    def __init__(self, session: Session, master: CanDriveMaster, controller: ServoController,
                 scenario: Scenario, config: ServoRunConfig, first: Feedback,
                 watch: SignalWatch | None = None) -> None:
        super().__init__("servo")
        self.session, self.master, self.controller = session, master, controller
        self.scenario = scenario
        self.loop = session.loop
        self.clock = session.clock
        self.split = config.realtime
        self.period_ns = self.loop.base_period_ns
        self.dt = self.period_ns / 1e9
        self.reference = ReferenceSamples(scenario.reference, self.dt)
        self.stats = TrackingStats(config.settle_s)
        self.prediction_every = config.prediction_period
        self.label = config.label
        # in lockstep a slow step costs no virtual time: no budget unless one is given
        self.budget_s = config.controller_budget_s or (STEP_BUDGET_S if self.split else None)
        self.watch = watch if watch is not None and watch.limits else None
        self.hu = getattr(getattr(controller, "config", None), "hu", None)
        self.predictor = controller if isinstance(controller, Predicting) else None
        self.commands = session.topic("/drive/command", COMMAND_SCHEMA, high_rate=True)
        self.feedbacks = session.topic("/drive/feedback", FEEDBACK_SCHEMA, high_rate=True)
        self.predictions = (session.topic("/mpc/prediction", PREDICTION_SCHEMA, high_rate=True)
                            if self.predictor is not None else None)
        self._feedback = first
        self._disturbance_ma = 0
        self._tick = 0
        self._t_s = 0.0
        self._input = first
        self._compute_us = 0.0
        self._last_path = ""
        self.late_writes = 0
        self.stale = 0

    def read(self, t_ns: int) -> Feedback:
        return self.master.receive_feedback() if self.split else self._feedback

    def compute(self, feedback: Feedback, t_ns: int) -> float:
        """The controller's step only: the tick is recorded after the command has left."""
        n = (t_ns - self.loop.start_ns) // self.period_ns
        self._tick, self._t_s = n, n * self.dt
        self._input = feedback
        u, self._compute_us = self._step(feedback.position_deg % 360.0, self._t_s)
        return u

    def write(self, command: float, t_ns: int) -> None:
        """Send the command (RPDO + SYNC), then record the tick: in real time the drive's
        answer travels while the tick is logged, checked and the loop sleeps."""
        if self.scenario.disturbance is not None:
            self._inject_disturbance(self._disturbance_for(self._t_s))
        if self.split:
            self.master.send_command(command)
            if self.clock.time_ns() > self.loop.start_ns + (self._tick + 1) * self.period_ns:
                self.late_writes += 1
            self._record(command, t_ns)
        else:
            # lockstep: the exchange returns the next tick's feedback; record this one first
            self._record(command, t_ns)
            self._feedback = self.master.exchange(command)

    def _record(self, u: float, t_ns: int) -> None:
        """KPIs, /drive/feedback, /drive/command, limits and the MPC prediction of this tick."""
        feedback, n, t_s = self._input, self._tick, self._t_s
        position = feedback.position_deg
        r = self.reference(n)
        error = wrap180(position - r)
        if not feedback.fresh:
            self.stale += 1
        self.stats.add(t_s, error, u, self._compute_us)
        message: dict[str, Any] = {"t_s": t_s, "reference_deg": r, "error_deg": error,
                                   "command_mA": u, "compute_us": self._compute_us}
        if self.scenario.disturbance is not None:
            message["disturbance_mA"] = self._disturbance_for(t_s)
        path = self._solver_path()
        if path:
            message["path"] = path
        self.feedbacks.log(t_ns, {
            "position_deg": position, "velocity_deg_s": feedback.velocity_deg_s,
            "current_mA": feedback.current_ma, "command_mA": feedback.command_ma,
            "statusword": feedback.statusword, "cycle": feedback.cycle,
            "fresh": feedback.fresh, "rtt_us": feedback.rtt_us})
        self.commands.log(t_ns, message)
        if self.watch is not None:
            self._check_limits(error, u, feedback)
        if self.predictor is not None and self.predictions is not None \
                and n % self.prediction_every == 0:
            u_pred, y_pred = self.predictor.prediction()
            # the arrays as they are: the writer process converts them (CDR float32 by default)
            self.predictions.log(t_ns, {"t_s": t_s, "u_mA": u_pred[: self.hu], "y_deg": y_pred})

    # -- helpers -----------------------------------------------------------------------
    def _step(self, position: float, t_s: float) -> tuple[float, float]:
        """The controller's command and its compute time [us]; a raise, a command that is not
        a finite number or a step over budget is a ControllerError (on ``/events`` too)."""
        try:
            u, elapsed = guarded_call(self.label, "step", self.controller.step, position, t_s,
                                      budget_s=self.budget_s)
            if isinstance(u, bool) or not isinstance(u, int | float | np.number) \
                    or not math.isfinite(u):
                raise ControllerError(f"controller {self.label!r}: step() must return a finite "
                                      f"current in mA, got {type(u).__name__} {u!r:.60}")
        except ControllerError as exc:
            self.session.event("controller.error", str(exc), level="error",
                               source="controller", t_s=t_s)
            raise
        return float(u), elapsed * 1e6

    def _check_limits(self, error: float, command: float, feedback: Feedback) -> None:
        assert self.watch is not None
        violation = self.watch.check({"abs_error_deg": abs(error),
                                      "abs_command_mA": abs(command),
                                      "abs_velocity_deg_s": abs(feedback.velocity_deg_s),
                                      "position_deg": feedback.position_deg})
        if violation is not None:
            self.session.event("limit.abort", f"limit violated, run stopped: "
                               f"{violation.describe()}", level="error", source="limits",
                               limit=str(violation.limit), measured=violation.measured,
                               t_s=self._t_s)
            self.loop.stop(f"limit {violation.limit}")

    def _disturbance_for(self, t_s: float) -> int:
        return round(self.scenario.disturbance(t_s)) if self.scenario.disturbance else 0

    def _inject_disturbance(self, value: int) -> None:
        """Scenario torque through the emulated drive's 0x2003 (by SDO, only on a change):
        applied from the next SYNC on, i.e. while u(k) is, as in the offline simulation."""
        if value == self._disturbance_ma:
            return
        self.master.sdo_write(DISTURBANCE_OBJECT, 0, value, "<h")
        self._disturbance_ma = value
        self.session.event("servo.disturbance", f"disturbance torque {value} mA",
                           source="scenario", torque_mA=value, t_s=self._t_s)

    def _solver_path(self) -> str:
        solver = getattr(self.controller, "solver", None)
        path = getattr(solver, "last_path", "") if solver is not None else ""
        pop = getattr(self.controller, "pop_events", None)
        if pop is not None:  # the explicit MPC reports its fallbacks itself
            for event in pop():
                event = dict(event)
                kind, message = event.pop("kind"), event.pop("message")
                level = event.pop("level", "warning")
                self.session.event(f"empc.{kind.removeprefix('empc_')}", message, level=level,
                                   source="empc", **event)
        elif path == "fallback" and self._last_path != "fallback":
            self.session.event("mpc.fallback", "MPC: the QP had no solution (infeasible "
                               "constraints): solved without the output constraints or held "
                               "the input", level="warning", source="mpc", t_s=self._t_s)
        self._last_path = path
        return path


# ------------------------------------------------------------------------------------- run
def drive_settings(config: ServoRunConfig) -> DriveConfig:
    """The drive config of the run: default < ``drive_config`` file < flags < overrides."""
    flags = {"master": {"current_limit_mA": float(config.umax), "node_id": config.node}}
    drive = load_drive_config(config.drive_config, overrides=flags)
    if config.drive_overrides:
        drive = drive.laid_over(config.drive_overrides)
    period_us = round(drive.master.cycle_period_s * 1e6)
    if period_us * 1e-6 != SAMPLE_PERIOD_S:
        raise ConfigError(f"{drive.source}: master.cycle_period_us = {period_us}, but the servo "
                          f"controllers are designed for T = {SAMPLE_PERIOD_S * 1e6:g} us")
    if not config.realtime and config.drive != "emulated":
        timeout_us = round(drive.master.rx_timeout_s * 1e6)
        drive = drive.laid_over({"master": {
            "rx_timeout_us": max(timeout_us, LOCKSTEP_RX_TIMEOUT_US)}})
    return drive


def default_session_path(controller: str) -> str:
    return f"servo-{controller}-{time.strftime('%Y%m%d-%H%M%S')}.mcap"


def run_servo(config: ServoRunConfig,
              on_started: Callable[[CanDriveMaster], None] | None = None) -> ServoRunResult:
    """Run one servo session; ``on_started(master)`` is called once the drive is enabled.

    Drive errors (fault, link lost) stop the loop; the drive is put in its safe state, the
    session file is finished with the KPIs so far, and the error is raised with its path."""
    scenario = parse_scenario(config.reference)
    drive = drive_settings(config)
    params = {**drive.run.params, **config.params}
    # checked before the session starts: a spec that cannot load leaves no file behind
    factory, _ = controller_factory(config.controller, scenario.reference, params,
                                    method="step", application="servo")
    kpi_limits, signal_limits = split_limits([*drive.run.limits, *config.limits], SIGNALS)
    watch = SignalWatch(signal_limits)
    path = config.out or default_session_path(controller_short_name(config.label))
    clock = RealtimeClock() if config.realtime else SimClock()
    sessions: list[Session] = []
    early: list[tuple[str, str, dict[str, Any]]] = []  # events from before the session

    def relay(kind: str, message: str, **data: Any) -> None:
        if sessions:
            sessions[0].event(kind, message, **data)
        else:
            early.append((kind, message, data))

    # the drive is opened first: an unreachable drive leaves no empty session file behind
    master = open_drive(config.drive, drive, on_event=relay, realtime=config.realtime)
    run_info = {k: v for k, v in asdict(config).items()
                if k not in ("drive_overrides", "limits", "controller", "params")}
    run_info |= {"controller": config.label, "params": params,
                 "limits": [str(lim) for lim in (*kpi_limits, *signal_limits)]}
    try:
        session = Session(path, clock, SAMPLE_PERIOD_S, kind="servo",
                          config={"servo": run_info, "drive": drive.data},
                          config_text=drive.text,
                          config_name="drive.toml", recording=config.recording)
    except BaseException:
        master.close()
        raise
    sessions.append(session)
    for kind, message, data in early:
        session.event(kind, message, **data)
    try:
        controller = make_controller(config, scenario, session, params, factory)
    except BaseException:  # nothing ran: no session file is left behind
        master.close()
        session.discard()
        raise
    task: ServoTask | None = None
    error: HilError | None = None
    wall = 0.0
    try:
        master.open()
        master.configure()
        master.enable()
        first = master.receive_feedback()
        session.add_component(master)
        if scenario.disturbance is not None:
            check_disturbance_object(master)
        task = ServoTask(session, master, controller, scenario, config, first, watch)
        session.add_task(task)
        if on_started is not None:
            on_started(master)
        start = time.perf_counter()
        try:
            session.run(duration_s=config.duration_s)
        finally:
            wall = time.perf_counter() - start
    except HilError as exc:
        error = exc
    finally:
        try:
            master.close()
        finally:
            kpis = collect_kpis(config, scenario, session, master, task, wall, path, error)
            kpis.update(verdict(kpis, kpi_limits, watch))
            session.close(kpis=kpis)
    if error is not None:
        error.args = (f"{error} (session recorded to {path})",)
        raise error
    return ServoRunResult(kpis=kpis, loop=session.loop.summary(), path=path)


def check_disturbance_object(master: CanDriveMaster) -> None:
    """The disturbance scenario pushes the axis through the emulated drive's 0x2003."""
    try:
        master.sdo_write(DISTURBANCE_OBJECT, 0, 0, "<h")
    except SdoAbortError as exc:
        raise UsageError(
            "the disturbance scenario needs the emulated drive's disturbance torque object "
            f"0x2003 (a test hook), which this drive refuses: {exc}") from None


def collect_kpis(config: ServoRunConfig, scenario: Scenario, session: Session,
                 master: CanDriveMaster, task: ServoTask | None, wall_s: float,
                 path: str, error: HilError | None) -> dict[str, Any]:
    """The ``--json`` document: DESIGN.md's keys first, then context."""
    base: dict[str, Any] = {"controller": config.label}
    if task is not None:
        tracking = task.stats.kpis(reference_amplitude(scenario))
    else:
        tracking = {"max_error_deg": None, "max_error_pct": None, "rms_error_deg": None,
                    "cumulative_error_deg": None,
                    "step_us": {"median": 0.0, "p99": 0.0, "max": 0.0}, "peak_current_mA": None}
    peak = tracking.pop("peak_current_mA")
    base.update(tracking)
    loop = session.loop
    ticks = task.stats.ticks if task is not None else 0
    base["deadline_misses"] = (loop.skipped_ticks + task.late_writes
                               if task is not None and config.realtime else 0)
    base["ticks"] = ticks
    base["mcap"] = config.recording.first_file(path)
    simulated = ticks * SAMPLE_PERIOD_S
    base.update({
        "reference": config.reference,
        "drive": config.drive,
        "clock": session.clock.mode,
        "umax_mA": config.umax,
        "settle_s": config.settle_s,
        "peak_current_mA": peak,
        "stale_feedback": task.stale if task is not None else 0,
        "clamped_commands": master.stats.clamped_commands,
        "wall_s": round(wall_s, 4),
        "realtime_factor": round(simulated / wall_s, 2) if wall_s > 0 else None,
        "stop_reason": loop.stop_reason,
    })
    mpc = task.controller if task is not None else None
    if isinstance(mpc, TrajectoryMpc | ExplicitMpc):
        base.update({"ert": mpc.config.ert, "ht": mpc.config.ht, "hu": mpc.config.hu,
                     "hp": mpc.config.hp})
        counts = getattr(getattr(mpc, "solver", None), "counts", None)
        if counts is not None:
            base["solver_paths"] = dict(counts)
        fallbacks = getattr(mpc, "fallbacks", None)
        if fallbacks is not None:
            base["empc_fallbacks"] = int(fallbacks)
    faults = {"stale_feedback": base["stale_feedback"], "late_frames": master.stats.late_frames,
              "emcy": master.stats.emcy}
    base["faults"] = faults
    base["disturbed"] = bool(faults["stale_feedback"] or faults["emcy"])
    if error is not None:
        base["error"] = str(error)
    return base
