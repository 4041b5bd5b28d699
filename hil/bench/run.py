"""``hil bench run``: a controller closing the loop on the relay bench, recorded to MCAP.

:class:`BenchExperiment` is the bench's part of the run pipeline (:mod:`hil.core.run`). The loop
(base period 0.01 s) runs, in each phase, the tasks in this order:

1. [lockstep emulator] plant step, the sampler (meter and levels, safety service; it records
   ``/bench/power``, ``/bench/levels``, ``/bench/relays``), the link monitor and the sequence
   player (M1/M2) - the rig's tasks (:mod:`hil.bench.rig`);
2. ``estimator`` (100 Hz): the sample for the KPIs and the controller's estimator (the EEC's
   Kalman filter), fed the relays held during the last step and this reading;
3. ``limits`` (100 Hz, only with per-tick limits): stops the run at the first violation;
4. ``controller`` (every 100 ticks = 1 s): the controller (EEC, BC or a user's, see
   :mod:`hil.controllers.base`) decides P1/P2 through the safety layer; the EEC's plan goes to
   ``/eec/plan``, fallbacks and solver trouble to ``/events``.

Tasks 2-4 are :mod:`hil.bench.control`'s. KPIs (:mod:`hil.bench.kpis`) are computed from the
samples the loop saw and stored in the session (``hil report`` prints them).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from hil.bench.config import BenchConfig, EecConfig, default_text
from hil.bench.control import (
    BenchContext,
    ControllerTask,
    GuardedController,
    Observer,
    RunLog,
    SignalLimits,
)
from hil.bench.kpis import BenchKpis, BenchRunKpis
from hil.bench.openers import OpenedBench, is_emulated, open_bench_device, planned_clock
from hil.bench.options import BenchRunOptions
from hil.bench.rig import BenchRig, attach_rig
from hil.bench.safety import BenchSafetyTask
from hil.bench.sequence import SequenceOrigin
from hil.bench.settings import BenchSettings, resolve_bench
from hil.bench.tunables import add_bench_limits
from hil.core.clock import Clock
from hil.core.loop import Task
from hil.core.notice import warn
from hil.core.plugins import build_controller, controller_factory, controller_short_name
from hil.core.ranges import MAX_DURATION_S, MAX_EEC_HORIZON_S, check_at_most, check_duration
from hil.core.run import (
    EventBuffer,
    Experiment,
    RunPlan,
    RunResult,
    TunerStarted,
    controller_budget,
    default_session_path,
    run_experiment,
)
from hil.core.session import Session
from hil.core.settings import settings_json
from hil.core.tuning import Tuner, add_controller
from hil.core.verdict import SignalWatch, split_limits
from hil.errors import (
    ConfigError,
    ForeignMasterError,
    HilError,
    SafetyStopError,
    UsageError,
)


def run_bench(opts: BenchRunOptions, *, tuner_started: TunerStarted | None = None
              ) -> RunResult:
    """Run one closed-loop bench session (``hil bench run``); ``tuner_started(tuner)`` is
    called with the run's tuner before the first tick (:mod:`hil.core.tuning`)."""
    return run_experiment(BenchExperiment(opts), tuner_started=tuner_started)


@dataclass(frozen=True, kw_only=True)
class BenchPlan(RunPlan):
    """A bench run, decided before anything opens: the pipeline's
    :class:`~hil.core.run.RunPlan` (its ``label`` the controller's) and the bench's own."""

    settings: BenchSettings
    params: Mapping[str, Any]
    factory: Callable[..., Any]   # the controller's, loaded and checked

    @property
    def bench(self) -> BenchConfig:
        return self.settings.bench

    @property
    def eec(self) -> EecConfig:
        return self.settings.eec

    @property
    def step_s(self) -> float:
        """The controller's decision step [s]."""
        return self.settings.eec.eec.step_s


@dataclass
class BenchState:
    """What a bench run opened and built, step by step."""

    device: OpenedBench | None = None
    log: RunLog | None = None
    origin: SequenceOrigin | None = None
    controller: GuardedController | None = None
    rig: BenchRig | None = None
    observer: Observer | None = None
    safety: BenchSafetyTask | None = None


def plan_bench(opts: BenchRunOptions) -> BenchPlan:
    """Everything a bench run decides before it opens anything; a HilError on bad input."""
    if opts.hp_s is not None:
        check_at_most(opts.hp_s, MAX_EEC_HORIZON_S, "--hp", "the EEC's MILP grows with "
                      "the horizon (a decision would take far longer than its step)")
    settings = resolve_bench(opts)
    url = settings.url
    if opts.disturbance and not is_emulated(url):
        raise UsageError("--disturbance switches the emulator's unknown load on: it needs "
                         "the emulated bench")
    bench, eec = settings.bench, settings.eec
    seconds = run_seconds(opts, bench)
    params = {**bench.run.params, **opts.params}
    kpi_limits, signal_limits = split_limits(
        [*bench.run.limits, *opts.limits],
        [*bench.map.meter_quantities, *bench.map.level_names], BenchRunKpis.limit_names())
    # checked before anything is opened: a spec that cannot load leaves no file behind
    factory, label = controller_factory(opts.controller, params, method="decide",
                                        application="bench")
    out = opts.out or default_session_path("bench", controller_short_name(label))
    run_info = opts.record() | {
        "controller": label, "params": params,
        "limits": [str(lim) for lim in (*kpi_limits, *signal_limits)]}
    text = "\n".join(filter(None, [default_text("bench.toml"), default_text("eec.toml"),
                                   bench.user_text]))
    return BenchPlan(
        # lockstep unless --realtime; a bench URL keeps it only where hil's emulator answers
        kind="bench", label=label, session_path=out, clock=planned_clock(opts.realtime),
        base_period_s=bench.sampling.period_s, duration_s=seconds,
        kpi_limits=tuple(kpi_limits), watch=SignalWatch(signal_limits),
        config={"bench": bench.data, "controllers": eec.data, "run": run_info,
                "settings": settings_json(settings.settings())},
        config_text=text, recording=opts.recording,
        devices=() if is_emulated(url) else (("bench", url),), quiet=opts.quiet,
        settings=settings, params=params, factory=factory)


def run_seconds(opts: BenchRunOptions, bench: BenchConfig) -> float:
    """How long the run lasts [s of session time]: ``--duration``, else ``--cycles`` machine
    cycles; a UsageError when it is shorter than a sample or longer than a run can be."""
    if opts.duration_s is not None:
        check_duration(opts.duration_s, "--duration", bench.sampling.period_s)
        return float(opts.duration_s)
    seconds = opts.cycles * bench.problem.sequence.period_s
    if seconds > MAX_DURATION_S:
        raise UsageError(f"--cycles {opts.cycles}: {seconds:g} s is longer than a run can "
                         f"be ({MAX_DURATION_S:g} s, about {MAX_DURATION_S / 86400:.1f} days)")
    return seconds


def cycles_run(opts: BenchRunOptions, bench: BenchConfig) -> float:
    """The machine cycles a run lasts (the KPI ``cycles``): ``--cycles``, or the share of
    cycles ``--duration`` makes (10 s of a 28 s cycle: 0.3571)."""
    if opts.duration_s is None:
        return opts.cycles
    return round(opts.duration_s / bench.problem.sequence.period_s, 4)


class BenchExperiment(Experiment[BenchPlan]):
    """``hil bench run`` as the run pipeline drives it: its frozen :class:`BenchPlan`
    (``planned``) and what each step opened or built (``state``)."""

    def __init__(self, opts: BenchRunOptions) -> None:
        self.opts = opts
        self.state = BenchState()

    def plan(self) -> BenchPlan:
        return plan_bench(self.opts)

    def open_devices(self, clock: Clock, on_event: EventBuffer) -> None:
        plan = self.planned
        for kind, message in plan.settings.notices:
            warn(message)
            on_event(kind, message, level="warning", source="settings")
        self.state.device = open_bench_device(plan.settings.url, plan.bench, clock, on_event)

    def session_clock(self, planned: Clock) -> Clock:
        device = self.state.device
        return (device.clock if device is not None else None) or planned

    def build_controller(self, session: Session) -> None:
        opts, plan, state = self.opts, self.planned, self.state
        bench = plan.bench
        problem = bench.problem
        state.log = RunLog(BenchKpis(problem, sample_period_s=bench.sampling.period_s,
                                     limit_va=plan.eec.eec.limit_va))
        state.origin = SequenceOrigin(session.clock)
        context = BenchContext(problem, plan.step_s, session, state.log, state.origin, plan.eec)
        controller = build_controller(plan.factory, plan.label, plan.params, method="decide",
                                      application="bench", context=context)
        budget = controller_budget(opts.controller_budget_s,
                                   session.clock.mode == "realtime", plan.step_s)
        state.controller = GuardedController(controller, plan.label, problem.peripherals,
                                             state.log, session.event, budget)

    def start(self, session: Session) -> None:
        plan, state = self.planned, self.state
        device, controller, log, origin = state.device, state.controller, state.log, state.origin
        assert device is not None and controller is not None  # opened and built before
        assert log is not None and origin is not None
        bench = plan.bench
        rig = state.rig = attach_rig(session, bench, device, play_sequence=True)
        session.recorder.metadata("bench", device.describe())
        origin.player = rig.player
        state.observer = Observer(rig, log, origin, controller.estimator)
        tasks: list[Task] = [state.observer]
        if plan.watch.limits:
            tasks.append(SignalLimits(rig, plan.watch, session))
        state.safety = BenchSafetyTask(bench.safety, rig.sampler, session,
                                       bench.sampling.period_s, origin)
        tasks.append(state.safety)
        tasks.append(ControllerTask(
            round(plan.step_s / bench.sampling.period_s), session.loop.base_period_ns,
            rig, bench.problem.peripherals, controller, origin,
            asynchronous=session.clock.mode == "realtime"))
        for task in tasks:
            session.add_task(task)

    def tunables(self, tuner: Tuner) -> None:
        """The controller's parameters (``controller.NAME``: the EEC's weights and horizon,
        applied from its next decision) and the safety limits (``safety.NAME``, only
        stricter)."""
        state = self.state
        if state.controller is not None:
            add_controller(tuner, state.controller.controller)
        if state.safety is not None:
            add_bench_limits(tuner, state.safety)

    def finish(self, session: Session) -> None:
        state = self.state
        assert state.observer is not None and state.rig is not None  # started
        state.observer.finish(state.rig.link.gave_up)
        if state.safety is not None and state.safety.stopped is not None:
            raise SafetyStopError(state.safety.stopped)
        if state.rig.link.foreign is not None:
            raise ForeignMasterError(state.rig.link.foreign)

    def close_devices(self) -> None:
        if self.state.rig is not None:
            self.state.rig.close()
        elif self.state.device is not None:
            self.state.device.close()

    def kpis(self, session: Session, wall_s: float, error: HilError | None) -> BenchRunKpis:
        plan, state = self.planned, self.state
        if state.log is None:
            raise ConfigError("the run recorded no meter or level samples: nothing to evaluate")
        kpis = kpis_of(state.log, self.opts, plan.label, plan.session_path,
                       cycles_run(self.opts, plan.bench))
        loop = session.loop
        kpis.stop_reason = loop.stop_reason
        kpis.wall_s = round(wall_s, 4)
        # simulated time over the time the loop ticked (None before a tick)
        kpis.realtime_factor = (round(loop.ticks * loop.base_period_ns / 1e9 / loop.ticking_s, 2)
                                if loop.ticking_s > 0 else None)
        if state.rig is not None:
            report = link_report(state.rig, session.clock.time_ns())
            kpis.faults, kpis.disturbed = report.faults, report.disturbed
        return kpis


@dataclass
class LinkReport:
    """How the bench link fared: the lost intervals (clock ns), whether the run gave up on
    it, and the fault KPIs (``faults``, ``disturbed``)."""

    lost: list[tuple[int, int]]
    gave_up: bool
    faults: dict[str, Any]
    disturbed: bool


def link_report(rig: BenchRig, end_ns: int) -> LinkReport:
    lost = rig.link.intervals(end_ns)
    stats = rig.bench.stats
    faults = {
        "link_losses": stats.link_losses, "reconnections": stats.reconnections,
        "link_down_s": round(sum(b - a for a, b in lost) / 1e9, 2),
        "failed_polls": stats.failed_polls, "retries": rig.bench.retries,
        "failed_writes": stats.failed_writes, "stuck_relays": stats.stuck_relays,
        "stale_readings": rig.sampler.stale.episodes if rig.sampler.stale else 0,
        "bad_readings": rig.sampler.bad.readings,
    }
    disturbed = any(faults[k] for k in ("link_losses", "failed_polls", "failed_writes",
                                        "stuck_relays", "stale_readings", "bad_readings"))
    return LinkReport(lost, rig.link.gave_up, faults, disturbed)


def kpis_of(log: RunLog, opts: BenchRunOptions, label: str, out: str, cycles: float
            ) -> BenchRunKpis:
    """The run's KPIs over the ``cycles`` machine cycles it lasted."""
    if not log.kpis.power_samples or not log.kpis.level_samples:
        raise ConfigError("the run recorded no meter or level samples: nothing to evaluate")
    times = log.solve_ms if log.solver_reports else log.decide_ms
    solve_ms = {"median": round(times.percentile(50), 3), "p99": round(times.percentile(99), 3),
                "max": round(times.max_us, 3)}
    return BenchRunKpis(controller=label, cycles=cycles, solve_ms=solve_ms,
                        solves_at_limit=log.solver_limits, max_gap=log.max_gap,
                        fallbacks=log.fallbacks,
                        mcap=opts.recording.first_file(out)).lay(log.kpis.kpis(cycles))

