"""One run pipeline for every application: plan -> devices -> session -> controller -> loop ->
KPIs -> verdict -> result.

An application describes one run as an :class:`Experiment` (``hil.bench.run``,
``hil.servo.run``); :func:`run_experiment` drives every run the same way, from the command
line, the Python API, the sweep and the pytest fixtures alike:

1. ``plan()`` - everything decided before anything is opened: configs parsed, the controller
   spec loaded and checked, limits split into KPI limits and per-tick signal limits, the clock,
   the session file. A bad value ends here, with no device touched and no file left.
2. ``open_devices(clock, on_event)`` - reach the hardware (or start its emulator) and leave it
   in its safe state. Events go to a buffer until the session exists. An unreachable device
   leaves no session file behind.
3. The session is created (its metadata and config attachment), written to a staging file
   beside its path (:mod:`hil.core.recording.output`).
4. ``build_controller(session)`` - the controller, guarded.
5. ``start(session)`` - enable the devices and add the loop's tasks (after the session is
   prepared: its writer up, the loop thread hardened in real time, so that the loop's first
   tick follows the enabling at once); ``tunables(tuner)``
   registers what may change while the run runs on the run's :class:`~hil.core.tuning.Tuner`
   (applied at the loop's tick boundaries), the live view (``--live``) serves it
   (:mod:`hil.core.recording.tune_wire`), and ``tuner_started(tuner)``, when the run was given
   one, attaches a transport to it (:mod:`hil.core.tuning`); then the session file is put at
   its path and the loop runs. A :class:`~hil.errors.HilError` (a fault, a lost link, a
   controller error) stops it; the loop has put every device in its safe state. A run that
   ends before its loop started, whichever step refused it, leaves no file (``mcap`` is None)
   and its path as it was.
6. ``finish(session)``, ``close_devices()``, ``kpis(...)``, the verdict of the limits, the
   run's ``status`` (:data:`hil.core.verdict.STATUSES`; ``unsafe``, and the KPIs' ``unsafe``
   lines, when a device said its outputs are not known to be safe:
   :data:`~hil.core.verdict.UNSAFE_EVENTS`), the file finished with the KPIs. An
   error (a Ctrl-C outside the loop becomes a :class:`RunInterruptedError`) is raised again
   with the session's path in its message and the :class:`RunResult` so far as its
   ``result``, for the run's report.

The result is a :class:`RunResult`. Rules every run shares live here too: where a session goes
by default (:func:`default_session_path`) and how long one controller call may take
(:func:`controller_budget`).
"""

from __future__ import annotations

import abc
import os
import signal
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from hil.core.clock import Clock
from hil.core.device_lock import DeviceLock, lock_device
from hil.core.kpis import Kpis
from hil.core.notice import unsafe
from hil.core.progress import ProgressLine, wants_progress
from hil.core.recording.output import OutputClaim, claim_output
from hil.core.recording.recorder import RecordingOptions
from hil.core.recording.writer_fork import start_server
from hil.core.session import Session
from hil.core.tuning import Tuner
from hil.core.verdict import UNSAFE_EVENTS, Limit, SignalWatch, run_status, verdict
from hil.errors import HilError, RunInterruptedError

#: the folder (under the working folder) where a run's session goes unless ``--out`` says
SESSIONS_FOLDER = "sessions"


@dataclass(frozen=True)
class RunPlan:
    """What a run is, decided before anything is opened."""

    kind: str                      # the session's kind: "bench", "servo"
    label: str                     # the controller, as the KPIs name it
    session_path: str
    clock: Clock
    base_period_s: float
    duration_s: float
    kpi_limits: tuple[Limit, ...]  # checked on the KPIs when the run ends
    watch: SignalWatch             # limits on per-tick signals, checked in the loop
    config: Mapping[str, Any]      # the session's config metadata (JSON)
    config_text: str | None = None  # the config as the user wrote it (an attachment)
    config_name: str = "config.toml"
    recording: RecordingOptions = field(default_factory=RecordingOptions)
    devices: tuple[tuple[str, str], ...] = ()  # (what, URL) of each device locked for the run
    quiet: bool = False            # no progress line on the terminal


@dataclass(frozen=True)
class RunResult:
    """What a run gives back: the KPI document (``--json``, the verdict's keys included), the
    verdict alone (``{}`` without limits), the session's first file, why the loop stopped and
    the loop's timing per task."""

    kpis: dict[str, Any]
    verdict: dict[str, Any]
    session_path: str | None  # None: the run never started, no session was recorded
    stop_reason: str
    loop: dict[str, Any]

    @property
    def passed(self) -> bool | None:
        """True: every limit holds; False: one is violated; None: the run had no limits."""
        return self.verdict.get("passed")


class EventBuffer:
    """An event sink (:data:`hil.contracts.EventSink`) for devices opened before their
    session: events are held, then replayed into the session once it exists. An event that
    makes the run unsafe (:data:`~hil.core.verdict.UNSAFE_EVENTS`) is a ``hil: unsafe:`` line
    on the terminal at once, and its message is kept (``unsafe``)."""

    def __init__(self) -> None:
        self._held: list[tuple[str, str, dict[str, Any]]] = []
        self._session: Session | None = None
        self.unsafe: list[str] = []

    def __call__(self, kind: str, message: str, **data: Any) -> None:
        if kind in UNSAFE_EVENTS:
            self.unsafe.append(message)
            unsafe(message)
        if self._session is not None:
            self._session.event(kind, message, **data)
        else:
            self._held.append((kind, message, data))

    def attach(self, session: Session) -> None:
        """From now on, events go to ``session``; the held ones first."""
        self._session = session
        for kind, message, data in self._held:
            session.event(kind, message, **data)
        self._held.clear()


PlanT = TypeVar("PlanT", bound=RunPlan)


class Experiment(abc.ABC, Generic[PlanT]):
    """One run of an application, as :func:`run_experiment` drives it (see the module).
    ``PlanT``: the application's frozen plan (a :class:`RunPlan`), which :meth:`decide` keeps
    as :attr:`planned` for the later steps."""

    _planned: PlanT | None = None

    @abc.abstractmethod
    def plan(self) -> PlanT:
        """Check and decide everything that needs no I/O; raise a HilError on bad input."""

    def decide(self) -> PlanT:
        """:meth:`plan`, kept as :attr:`planned` (the pipeline's first step)."""
        self._planned = self.plan()
        return self._planned

    @property
    def planned(self) -> PlanT:
        """The run's plan, once :meth:`decide` made it."""
        if self._planned is None:
            raise RuntimeError(f"{type(self).__name__}: the run is not planned yet")
        return self._planned

    @abc.abstractmethod
    def open_devices(self, clock: Clock, on_event: EventBuffer) -> None:
        """Reach the devices (or start their emulators), outputs in their safe state."""

    def session_clock(self, planned: Clock) -> Clock:
        """The clock the session runs on, asked once the devices are open: ``planned`` unless
        opening them decided otherwise (a bench URL keeps lockstep only where hil's emulator
        answers). Default: ``planned``."""
        return planned

    @abc.abstractmethod
    def build_controller(self, session: Session) -> None:
        """Build the controller (guarded): a failure leaves no session file."""

    @abc.abstractmethod
    def start(self, session: Session) -> None:
        """Enable the devices and add the loop's tasks and safe-state components."""

    def tunables(self, tuner: Tuner) -> None:
        """Register what may change while the run runs (after :meth:`start`). Default:
        nothing."""
        return None

    def finish(self, session: Session) -> None:
        """After a loop that ended without error, before the devices close. Default: none."""
        return None

    @abc.abstractmethod
    def close_devices(self) -> None:
        """Release the devices (the loop already put them in their safe state); idempotent."""

    @abc.abstractmethod
    def kpis(self, session: Session, wall_s: float, error: HilError | None) -> Kpis:
        """The run's KPIs so far (its :class:`~hil.core.kpis.Kpis`: the ``--json``
        document), ``stop_reason`` included."""


#: the hook a transport attaches to a run's tuner with (:mod:`hil.core.tuning`)
TunerStarted = Callable[[Tuner], None]


def run_experiment(experiment: Experiment[Any], *,
                   tuner_started: TunerStarted | None = None) -> RunResult:
    """Run ``experiment`` through the pipeline (see the module); its :class:`RunResult`.
    ``tuner_started(tuner)``: called with the run's tuner just before the loop's first tick.

    A HilError that stopped the loop is raised again after the session file is finished with
    the KPIs so far, its message ending with the session's path, its ``result`` the
    :class:`RunResult` so far."""
    plan = experiment.decide()
    if not plan.recording.in_process:  # the writers' fork server starts beside the devices
        start_server()
    # the file is checked and locked before any device is reached, and each device locked
    output = claim_output(plan.recording.first_file(plan.session_path))
    locks: list[DeviceLock] = []
    try:
        locks.extend(lock_device(url, what) for what, url in plan.devices)
    except BaseException:
        output.abandon()
        raise
    try:
        return _run_locked(experiment, plan, output, tuner_started)
    finally:
        for lock in locks:
            lock.release()


def _run_locked(experiment: Experiment[Any], plan: RunPlan, output: OutputClaim,
                tuner_started: TunerStarted | None) -> RunResult:
    events = EventBuffer()
    try:
        experiment.open_devices(plan.clock, events)
    except BaseException:
        output.abandon()
        raise
    try:
        session = Session(plan.session_path, experiment.session_clock(plan.clock),
                          plan.base_period_s, kind=plan.kind,
                          config=dict(plan.config), config_text=plan.config_text,
                          config_name=plan.config_name, recording=plan.recording,
                          output=output, tunable=True)
    except BaseException:
        experiment.close_devices()
        output.abandon()
        raise
    events.attach(session)
    try:
        experiment.build_controller(session)
    except BaseException:  # nothing ran: no session file is left behind
        experiment.close_devices()
        session.close()
        raise
    error: HilError | None = None
    wall_s = 0.0
    kpis: dict[str, Any] = {}
    outcome: dict[str, Any] = {}
    progress = None
    tuner = Tuner(event=session.event, topic=session.topic, time_ns=session.clock.time_ns,
                  lockstep=session.clock.mode == "sim")
    try:
        session.prepare()  # the writer up and the loop thread hardened before any enabling
        experiment.start(session)
        experiment.tunables(tuner)
        session.loop.at_boundary = tuner.tick
        session.recorder.serve_parameters(tuner)  # the live view's parameters (with --live)
        if tuner_started is not None:
            tuner_started(tuner)
        if wants_progress(plan.quiet):
            progress = ProgressLine(f"{plan.kind} {plan.label}", plan.duration_s,
                                    max(1, round(0.1 / plan.base_period_s)))
            session.add_task(progress)
        begin = time.perf_counter()
        try:
            session.run(duration_s=plan.duration_s)
        finally:
            tuner.close()
            wall_s = time.perf_counter() - begin
            if progress is not None:
                progress.clear()
        experiment.finish(session)
    except HilError as exc:
        error = exc
    except KeyboardInterrupt:  # outside the loop (enabling, finishing): the loop takes its own
        error = _interrupted("SIGINT", session.loop.ticks)
    finally:
        tuner.close()
        try:
            experiment.close_devices()
        finally:
            try:
                error = error or _signal_error(session)
                kpis = _kpis(experiment, plan, session, wall_s, error)
                if events.unsafe:  # the devices' outputs are not known to be safe
                    kpis["unsafe"] = list(events.unsafe)
                outcome = verdict(kpis, plan.kpi_limits, plan.watch)
                kpis.update(outcome)
                kpis["status"] = run_status(kpis, error)
                if not session.started:  # refused before its first tick: no session file
                    kpis["mcap"] = None
            finally:
                session.close(kpis=kpis or None)
    recorded = plan.recording.first_file(plan.session_path) if session.started else None
    result = RunResult(kpis, outcome, recorded, session.loop.stop_reason or "completed",
                       session.loop.summary())
    if error is not None:
        if recorded is not None:
            error.args = (f"{error} (session recorded to {plan.session_path})",)
        error.result = result
        raise error
    return result


def _signal_error(session: Session) -> RunInterruptedError | None:
    """The error of a loop a signal (Ctrl-C, SIGTERM) stopped; None for any other end."""
    stop_reason = session.loop.stop_reason or ""
    if not stop_reason.startswith("signal "):
        return None
    return _interrupted(stop_reason.removeprefix("signal "), session.loop.ticks)


def _interrupted(name: str, ticks: int) -> RunInterruptedError:
    """A run stopped by the signal ``name``; its exit status is the shell's for it."""
    return RunInterruptedError(
        f"interrupted by {name} after {ticks} tick(s): the hardware is in its safe state, the "
        "KPIs so far are in the session", 128 + getattr(signal.Signals, name, signal.SIGINT).value)


def _kpis(experiment: Experiment[Any], plan: RunPlan, session: Session, wall_s: float,
          error: HilError | None) -> dict[str, Any]:
    """The experiment's KPIs; after an error, what can be had (the error is what matters),
    with the controller, the session and the error line at least."""
    try:
        kpis = experiment.kpis(session, wall_s, error).document()
    except HilError:
        if error is None:
            raise
        kpis = {}
    kpis.setdefault("controller", plan.label)
    kpis.setdefault("mcap", plan.recording.first_file(plan.session_path))
    kpis.setdefault("stop_reason", session.loop.stop_reason)
    if error is not None:
        kpis["error"] = str(error)
    return kpis


def default_session_path(kind: str, controller: str, folder: str = SESSIONS_FOLDER) -> str:
    """``sessions/KIND-CONTROLLER-YYYYmmdd-HHMMSS.mcap`` under the working folder (``-2``,
    ``-3``... when that name is taken)."""
    stem = os.path.join(folder, f"{kind}-{controller}-{time.strftime('%Y%m%d-%H%M%S')}")
    path, n = f"{stem}.mcap", 1
    while os.path.exists(path):
        n += 1
        path = f"{stem}-{n}.mcap"
    return path


def controller_budget(given: float | None, realtime: bool, default_s: float) -> float | None:
    """The time one controller call may take: as given; else, in real time, the
    application's ``default_s``. In lockstep a slow call costs no virtual time: no budget
    unless one is given."""
    if given is not None:
        return given
    return default_s if realtime else None
