"""``hil bench run``: a controller closing the loop on the relay bench, recorded to MCAP.

Loop (base period 0.01 s, tasks in this order every tick):

1. [lockstep emulator] plant step, 2. sampler (meter and levels, safety service; publishes
   ``/bench/power``, ``/bench/levels``, ``/bench/relays``) - both from :func:`attach_bench`;
3. ``estimator`` (100 Hz): logs the sample for the KPIs and feeds the controller's estimator
   (the EEC's Kalman filter) the relays held during the last step and this reading;
4. ``sequence``: the machining sequence player (M1/M2);
5. ``limits`` (100 Hz, only with per-tick limits): stops the run at the first violation;
6. ``controller`` (every 100 ticks = 1 s): the controller (EEC, BC or a user's, see
   :mod:`controllers.base`) decides P1/P2 through the safety layer; the EEC's plan goes to
   ``/eec/plan``, fallbacks and solver trouble to ``/events``.

Tasks 3, 5 and 6 are :mod:`hil.bench.control`'s. KPIs (:mod:`hil.bench.kpis`) are
computed from the samples the loop saw and stored in the session (``hil report`` prints them).
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

from controllers.base import BenchController
from hil.bench.config import BenchConfig, default_text, load_configs
from hil.bench.control import (
    BenchContext,
    ControllerTask,
    GuardedController,
    Observer,
    RunLog,
    SignalLimits,
    estimator_of,
)
from hil.bench.kpis import BenchKpis
from hil.bench.rig import BenchRig, SequencePlayer, attach_bench, is_emulated, session_clock
from hil.core.errors import ConfigError, HilError, UsageError
from hil.core.plugins import build_controller, controller_factory, controller_short_name
from hil.core.recorder import RecordingOptions
from hil.core.session import Session
from hil.core.types import TimeSource
from hil.core.verdict import Limit, SignalWatch, split_limits, verdict


@dataclass
class BenchRunOptions:
    """Everything ``hil bench run`` can set (CLI flags); None = the config's value.

    ``controller`` is a spec (``eec``, ``bc``, ``FILE.py:Class``, ``package.module:Class``, a
    name registered in ``hil.controllers``) or a class; ``params`` are laid over the config's
    ``[controller]`` table; ``limits`` are added to its ``[limits]``."""

    controller: str | Callable[..., Any] = "eec"
    params: dict[str, Any] = field(default_factory=dict)
    bench: str = "emulated"
    cycles: int = 8
    hp_s: int | None = None
    hs_s: int | None = None
    gamma1: float | None = None
    gamma2: float | None = None
    dwell_s: float | None = None
    disturbance: bool = False
    realtime: bool = False
    out: str | None = None
    config_path: str | None = None
    seed: int | None = None
    limits: tuple[Limit, ...] = ()
    controller_budget_s: float | None = None  # per decision; None: the step in real time
    overrides: dict[str, Any] = field(default_factory=dict)  # [eec] keys (benchmarks, demo)
    recording: RecordingOptions = field(default_factory=RecordingOptions)

    def flags(self) -> dict[str, Any]:
        """The EEC's flags (``--hp``, ``--hs``, ``--gamma1``, ``--gamma2``)."""
        return {"hp_s": self.hp_s, "hs_s": self.hs_s, "gamma1": self.gamma1,
                "gamma2": self.gamma2}


class SequenceOrigin:
    """Clock time of the machining sequence's start, which every ``t_s`` counts from: the
    player's first tick (the clock's time until then)."""

    def __init__(self, clock: TimeSource) -> None:
        self.clock = clock
        self.player: SequencePlayer | None = None

    def __call__(self) -> int:
        t0 = self.player.t0_ns if self.player is not None else None
        return t0 if t0 is not None else self.clock.time_ns()


def run_bench(opts: BenchRunOptions) -> dict[str, Any]:
    """Run one closed-loop bench session; return the KPI dictionary (``hil bench run``)."""
    if opts.disturbance and not is_emulated(opts.bench):
        raise UsageError("--disturbance switches the emulator's unknown load on: it needs "
                         "--bench emulated")
    bench, eec = load_configs(opts.config_path, opts.overrides)
    bench = bench.with_dwell(opts.dwell_s)  # the safety layer enforces the controllers' dwell
    problem = bench.problem
    step_s = eec.eec.step_s
    params = {**bench.run.params, **opts.params}
    kpi_limits, signal_limits = split_limits(
        [*bench.run.limits, *opts.limits],
        [*bench.map.meter_quantities, *bench.map.level_names])
    # checked before the session starts: a spec that cannot load leaves no file behind
    factory, label = controller_factory(opts.controller, params, method="decide",
                                        application="bench")
    out = opts.out or os.path.join(tempfile.gettempdir(),
                                   f"hil-bench-{controller_short_name(label)}-{int(time.time())}.mcap")
    clock = session_clock(opts.bench, opts.realtime)
    run_info = {k: v for k, v in vars(opts).items()
                if k not in ("overrides", "limits", "recording")}
    run_info["recording"] = asdict(opts.recording)
    merged = {"bench": bench.data, "controllers": eec.data,
              "run": run_info | {"controller": label, "params": params,
                                 "limits": [str(lim) for lim in (*kpi_limits, *signal_limits)]}}
    text = "\n".join(filter(None, [default_text("bench.toml"), default_text("eec.toml"),
                                   bench.user_text]))
    session = Session(out, clock, bench.sampling.period_s, kind="bench", config=merged,
                      config_text=text, recording=opts.recording)
    log = RunLog(BenchKpis(problem, sample_period_s=bench.sampling.period_s,
                           limit_va=eec.eec.limit_va))
    origin = SequenceOrigin(clock)
    watch = SignalWatch(signal_limits)
    context = BenchContext(
        problem, step_s, session, log, origin,
        lambda p: load_configs(opts.config_path, {**opts.overrides, **p})[1], opts.flags())
    try:
        controller = build_controller(factory, label, params, method="decide",
                                      application="bench", context=context)
    except BaseException:  # nothing ran: no session file is left behind
        session.discard()
        raise
    guarded = GuardedController(controller, label, problem.peripherals, log, session.event,
                                controller_budget(opts.controller_budget_s, step_s, clock))
    try:
        link = _run(session, opts, bench, guarded, step_s, log, origin, watch)
    except HilError as exc:
        session.close()
        exc.args = (f"{exc} (session recorded to {out})",)
        raise
    except BaseException:
        session.close()
        raise
    kpis = kpis_of(log, opts, label, out)
    kpis["stop_reason"] = session.loop.stop_reason
    kpis.update(link.kpis)
    kpis.update(verdict(kpis, kpi_limits, watch))
    session.close(kpis=kpis)
    return kpis


def controller_budget(given: float | None, step_s: float, clock: TimeSource) -> float | None:
    """The time one decision may take: as given; else, in real time, the decision step. In
    lockstep a slow decision costs no virtual time, so none unless given."""
    if given is not None:
        return given
    return step_s if getattr(clock, "mode", "") == "realtime" else None


@dataclass
class LinkReport:
    """How the bench link fared: the lost intervals (clock ns), whether the run gave up on
    it, and the fault KPIs (``faults``, ``disturbed``)."""

    lost: list[tuple[int, int]]
    gave_up: bool
    kpis: dict[str, Any]


def link_report(rig: BenchRig, end_ns: int) -> LinkReport:
    lost = rig.link.intervals(end_ns)
    stats = rig.bench.stats
    faults = {
        "link_losses": stats.link_losses, "reconnections": stats.reconnections,
        "link_down_s": round(sum(b - a for a, b in lost) / 1e9, 2),
        "failed_polls": stats.failed_polls, "retries": rig.bench.retries,
        "failed_writes": stats.failed_writes, "stuck_relays": stats.stuck_relays,
        "stale_readings": rig.sampler.stale.episodes if rig.sampler.stale else 0,
    }
    disturbed = any(faults[k] for k in ("link_losses", "failed_polls", "failed_writes",
                                        "stuck_relays", "stale_readings"))
    return LinkReport(lost, rig.link.gave_up, {"faults": faults, "disturbed": disturbed})


def _run(session: Session, opts: BenchRunOptions, bench: BenchConfig,
         controller: BenchController, step_s: float, log: RunLog, origin: SequenceOrigin,
         watch: SignalWatch) -> LinkReport:
    rig = None
    try:
        rig = attach_bench(session, bench, opts.bench, play_sequence=False,
                           seed=opts.seed, disturbance=opts.disturbance or None)
        player = origin.player = SequencePlayer(rig.bench, rig.sequence,
                                                divisor=rig.sampler.divisor)
        problem = bench.problem
        observer = Observer(rig, log, origin, estimator_of(controller))
        session.add_task(observer)
        session.add_task(player)
        if watch.limits:
            session.add_task(SignalLimits(rig, watch, session))
        session.add_task(ControllerTask(
            round(step_s / bench.sampling.period_s), session.loop.base_period_ns, rig,
            problem.peripherals, controller, origin,
            asynchronous=session.clock.mode == "realtime"))
        session.run(duration_s=opts.cycles * problem.sequence.period_s)
        observer.finish(rig.link.gave_up)
        return link_report(rig, session.clock.time_ns())
    finally:
        if rig is not None:
            rig.close()


def kpis_of(log: RunLog, opts: BenchRunOptions, label: str, out: str) -> dict[str, Any]:
    if not log.kpis.power_samples or not log.kpis.level_samples:
        raise ConfigError("the run recorded no meter or level samples: nothing to evaluate")
    times = log.solve_ms if log.solver_reports else log.decide_ms
    solve_ms = {"median": round(times.percentile(50), 3), "p99": round(times.percentile(99), 3),
                "max": round(times.max_us, 3)}
    return {"controller": label, "cycles": opts.cycles, **log.kpis.kpis(opts.cycles),
            "solve_ms": solve_ms, "solves_at_limit": log.solver_limits,
            "max_gap": log.max_gap,
            "fallbacks": log.fallbacks, "mcap": opts.recording.first_file(out)}

