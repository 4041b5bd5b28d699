"""``hil bench run``: EEC or BC closed-loop against the relay bench, recorded to MCAP.

Loop (base period 0.01 s, tasks in this order every tick):

1. [lockstep emulator] plant step, 2. sampler (meter and levels, safety service; publishes
   ``/bench/power``, ``/bench/levels``, ``/bench/relays``) - both from :func:`attach_bench`;
3. ``estimator`` (100 Hz, EEC only): the Kalman filter, with the relays held during the last
   step and this reading;
4. ``sequence``: the machining sequence player (M1/M2);
5. ``controller`` (every 100 ticks = 1 s): EEC or BC decides P1/P2 through the safety layer;
   the EEC's plan goes to ``/eec/plan``, fallbacks and solver trouble to ``/events``.

KPIs (:mod:`controllers.bench_kpis`) are computed from the samples the loop saw and stored in
the session (``hil report`` prints them).
"""

from __future__ import annotations

import importlib.resources
import os
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from controllers.bc import BasicController
from controllers.bench_kalman import BenchKalman, KalmanSettings
from controllers.bench_kpis import bench_kpis, timing_summary
from controllers.bench_models import DeviceModel, MachiningModel, load_linear_model
from controllers.bench_problem import BenchProblem, load_problem
from controllers.eec import EEC, EECSettings, Observation
from controllers.eec_prediction import BenchEstimate, BenchModels
from hil.bench.rig import SequencePlayer, attach_bench, default_bench_config_text, load_bench_config
from hil.core.clock import RealtimeClock, SimClock
from hil.core.config import deep_merge, load_toml, lookup, parse_toml
from hil.core.errors import ConfigError, UsageError
from hil.core.loop import Task
from hil.core.session import Session

SOURCE = "eec config"
CONTROLLERS = ("eec", "bc")


@dataclass
class BenchRunOptions:
    """Everything ``hil bench run`` can set (CLI flags); None = the config's value."""

    controller: str = "eec"
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
    overrides: dict[str, Any] = field(default_factory=dict)  # [eec] keys (benchmarks, demo)


def default_eec_config_text() -> str:
    return importlib.resources.files("hil.configs").joinpath("eec.toml").read_text("utf-8")


def load_configs(path: str | None) -> tuple[dict[str, Any], dict[str, Any], str]:
    """(bench config, eec config, text of the user file or '') with the user file over both."""
    eec = parse_toml(default_eec_config_text(), "hil/configs/eec.toml")
    text = ""
    if path is not None:
        user, text = load_toml(path)
        eec = deep_merge(eec, user)
    return load_bench_config(path), eec, text


def model_path(name: str) -> str:
    """A model file: absolute, relative to the working directory, or next to eec.toml."""
    if os.path.isabs(name) or os.path.exists(name):
        return name
    packaged = importlib.resources.files("hil.configs").joinpath(name)
    if packaged.is_file():
        return str(packaged)
    raise ConfigError(f"{SOURCE}: model file {name!r} not found (working directory or "
                      "hil/configs)")


def load_models(eec_config: dict[str, Any], problem: BenchProblem) -> BenchModels:
    machining = load_linear_model(model_path(lookup(eec_config, "models.machining", str,
                                                    source=SOURCE)), "machining")
    devices = {}
    for name in problem.peripherals:
        path = model_path(lookup(eec_config, f"models.{name}", str, source=SOURCE))
        devices[name] = DeviceModel.from_linear(load_linear_model(path, name))
    models = BenchModels(MachiningModel.from_linear(machining, problem.sequence), devices)
    dts = {machining.dt, *(d.dt for d in devices.values())}
    if len(dts) != 1:
        raise ConfigError(f"{SOURCE}: every model must have the same dt, got {sorted(dts)}")
    return models


def eec_settings(eec_config: dict[str, Any], opts: BenchRunOptions) -> EECSettings:
    c = deep_merge(eec_config.get("eec", {}), opts.overrides)
    step = lookup(c, "step_s", float, 1.0, source=SOURCE)
    hp = opts.hp_s if opts.hp_s is not None else lookup(c, "hp_s", float, source=SOURCE)
    hs = opts.hs_s if opts.hs_s is not None else lookup(c, "hs_s", float, source=SOURCE)
    weight = lookup(c, "limit_weight", float, 10.0, source=SOURCE)
    try:
        return EECSettings(
            hp_steps=round(hp / step), hs_steps=round(hs / step), step_s=step,
            gamma1=opts.gamma1 if opts.gamma1 is not None else lookup(c, "gamma1", float,
                                                                      source=SOURCE),
            gamma2=opts.gamma2 if opts.gamma2 is not None else lookup(c, "gamma2", float,
                                                                      source=SOURCE),
            terminal=lookup(c, "terminal", str, "hold", source=SOURCE),
            limit_va=lookup(c, "limit_va", float, source=SOURCE) if weight > 0 else None,
            limit_weight=weight,
            peak_resolution_va=lookup(c, "peak_resolution_va", float, 1.0, source=SOURCE),
            time_limit_s=lookup(c, "time_limit_s", float, 0.5, source=SOURCE),
            mip_rel_gap=lookup(c, "mip_rel_gap", float, 1e-4, source=SOURCE),
        )
    except ValueError as exc:
        raise UsageError(str(exc)) from None


PLAN_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "hil.EECPlan",
    "description": "One MILP solve of the EEC: the relay plan over the horizon (1 value per "
                   "step), the predicted levels and power, solver status and time",
    "properties": {
        "t_s": {"type": "number", "description": "decision time since the sequence start"},
        "status": {"type": "string"},
        "solve_ms": {"type": "number"},
        "objective": {"type": "number"},
        "peak_va": {"type": "number", "description": "predicted highest total VA"},
        "energy_vas": {"type": "number", "description": "predicted area over the horizon"},
        "rows": {"type": "integer", "description": "J2 pattern rows after pruning"},
        "u": {"type": "object", "description": "relay plan per peripheral (0/1 per step)"},
        "q": {"type": "object", "description": "predicted level per resource (H+1 values)"},
        "power_va": {"type": "array", "items": {"type": "number"},
                     "description": "predicted highest total VA in each step"},
    },
}
ESTIMATE_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "hil.BenchEstimate",
    "description": "Kalman filter of the total VA at the decision instants",
    "properties": {"disturbance_va": {"type": "number"}, "output_va": {"type": "number"},
                   "innovation_va": {"type": "number"}},
}


@dataclass
class RunLog:
    """What the loop saw, kept for the KPIs (one entry per good sample)."""

    t: list[float] = field(default_factory=list)
    s: list[float] = field(default_factory=list)
    relays_t: list[float] = field(default_factory=list)
    relays: dict[str, list[bool]] = field(default_factory=dict)
    levels_t: list[float] = field(default_factory=list)
    levels: dict[str, list[float]] = field(default_factory=dict)
    solve_ms: list[float] = field(default_factory=list)
    fallbacks: int = 0
    solver_limits: int = 0


class Observer(Task):
    """Every sample: log the reading for the KPIs and, for the EEC, run the Kalman filter
    with the relays held during the last step (placed before the sequence player)."""

    def __init__(self, rig: Any, names: list[str], log: RunLog, clock_origin: Callable[[], int],
                 kalman: BenchKalman | None, machining_relays: tuple[str, ...]) -> None:
        super().__init__("estimator", 1)
        self.rig, self.names, self.log = rig, names, log
        self.kalman = kalman
        self.machining_relays = machining_relays
        self._origin = clock_origin
        self._last_power: Any = None
        self._last_levels: Any = None
        self._first = True

    def read(self, t_ns: int) -> None:
        sampler, bench = self.rig.sampler, self.rig.bench
        t = (t_ns - self._origin()) / 1e9
        relays = bench.relays()
        power = sampler.latest_power
        fresh = power is not None and power is not self._last_power
        self._last_power = power
        log = self.log
        log.relays_t.append(t)
        for name in self.names:
            log.relays.setdefault(name, []).append(relays[name])
        if fresh:
            log.t.append(t)
            log.s.append(power["total_va"])
        levels = sampler.latest_levels
        if levels is not None and levels is not self._last_levels:
            self._last_levels = levels
            log.levels_t.append(t)
            for name, value in levels.items():
                log.levels.setdefault(name, []).append(value)
        if self.kalman is not None:
            if not self._first:
                self.kalman.advance({r: relays[r] for r in self.machining_relays},
                                    {n: relays[n] for n in self.names})
            if fresh:
                self.kalman.correct(power["total_va"])
        self._first = False


@dataclass
class DecisionInput:
    """What a decision is made from, taken in the loop thread at the decision instant."""

    t_s: float                      # since the machining sequence started
    t_ns: int                       # clock time of the decision instant
    levels: dict[str, float]
    relays: dict[str, bool]         # peripherals, as the safety layer knows them
    estimate: BenchEstimate | None  # Kalman filter (EEC only)
    output_va: float = 0.0
    innovation_va: float = 0.0


Decide = Callable[[DecisionInput], dict[str, bool]]


class ControllerTask(Task):
    """Once per decision step: levels, relays (and the estimate) in, P1/P2 out through the
    safety layer.

    Lockstep: the decision is computed in the tick of the decision instant. Real time
    (``asynchronous``): the decision runs in a worker thread (HiGHS releases the GIL) so the
    loop keeps sampling at 100 Hz; its command is applied ``apply_delay_s`` after the
    decision instant, or when it is ready if later. The fixed delay keeps the spacing of
    the switches equal to the decision spacing, so the safety layer's dwell agrees with the
    controller's. A decision instant that finds the previous decision still running is
    skipped (counted in ``skipped``).
    """

    def __init__(self, step_ticks: int, tick_ns: int, rig: Any, problem: BenchProblem,
                 decide: Decide, origin: Callable[[], int], kalman: BenchKalman | None, *,
                 asynchronous: bool = False, apply_delay_s: float = 0.1) -> None:
        super().__init__("controller", 1 if asynchronous else step_ticks)
        self._step_ns = step_ticks * tick_ns
        self.rig, self.problem, self.decide = rig, problem, decide
        self.kalman = kalman
        self._origin = origin
        self.asynchronous = asynchronous
        self.apply_delay_s = apply_delay_s
        self.skipped = 0
        self._last_step = -1
        self._pending: tuple[Future[dict[str, bool]], int] | None = None
        self._executor = ThreadPoolExecutor(1, "eec") if asynchronous else None

    def _input(self, t_ns: int) -> DecisionInput | None:
        levels = self.rig.sampler.latest_levels
        if levels is None or not self.rig.bench.link_up:
            return None  # nothing to decide on: the safety layer holds the relays
        relays = self.rig.bench.relays()
        t = round((t_ns - self._origin()) / 1e9, 9)
        k = self.kalman
        return DecisionInput(t, t_ns, dict(levels),
                             {n: relays[n] for n in self.problem.peripherals},
                             k.estimate() if k else None, k.output_va if k else 0.0,
                             k.innovation if k else 0.0)

    def read(self, t_ns: int) -> Any:
        if not self.asynchronous:
            return self._input(t_ns)
        step = (t_ns - self._origin()) // self._step_ns
        if step > self._last_step:  # a decision instant (the first tick of a step)
            self._last_step = step
            if self._pending is not None:
                self.skipped += 1
            else:
                decision = self._input(t_ns)
                if decision is not None and self._executor is not None:
                    due = t_ns + round(self.apply_delay_s * 1e9)
                    self._pending = (self._executor.submit(self.decide, decision), due)
        if self._pending is not None and t_ns >= self._pending[1] and self._pending[0].done():
            future, _ = self._pending
            self._pending = None
            return future.result()
        return None

    def compute(self, measurement: Any, t_ns: int) -> dict[str, bool] | None:
        if isinstance(measurement, DecisionInput):
            return self.decide(measurement)
        return measurement

    def write(self, command: dict[str, bool] | None, t_ns: int) -> None:
        if command:
            current = self.rig.bench.commanded()
            changes = {n: on for n, on in command.items() if current[n] != on}
            if changes:
                self.rig.bench.set_relays(changes, t_ns)

    def safe_state(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._pending = None


def run_bench(opts: BenchRunOptions) -> dict[str, Any]:
    """Run one closed-loop bench session; return the KPI dictionary (``hil bench run``)."""
    if opts.controller not in CONTROLLERS:
        raise UsageError(f"controller must be one of {CONTROLLERS}, got {opts.controller!r}")
    if opts.disturbance and opts.bench != "emulated":
        raise UsageError("--disturbance switches the emulator's unknown load on: it needs "
                         "--bench emulated")
    bench_config, eec_config, user_text = load_configs(opts.config_path)
    problem = load_problem(bench_config, opts.dwell_s)
    for name, dwell in problem.dwell_s.items():  # the safety layer enforces the same dwell
        bench_config["relays"][name]["dwell_s"] = dwell
    settings = eec_settings(eec_config, opts)
    base = lookup(bench_config, "sampling.period_s", float, source="bench config")
    divisor = round(settings.step_s / base)
    if divisor < 1 or abs(divisor * base - settings.step_s) > 1e-9:
        raise ConfigError(f"{SOURCE}: eec.step_s = {settings.step_s} is not a multiple of the "
                          f"sampling period {base}")
    out = opts.out or os.path.join(tempfile.gettempdir(),
                                   f"hil-bench-{opts.controller}-{int(time.time())}.mcap")
    feedback = lookup(deep_merge(eec_config.get("eec", {}), opts.overrides), "feedback",
                      bool, True, source=SOURCE)
    models = load_models(eec_config, problem) if opts.controller == "eec" else None
    # lockstep needs the emulator: a real bench always runs on the wall clock
    clock = RealtimeClock() if opts.realtime or opts.bench != "emulated" else SimClock()
    merged = {"bench": bench_config, "controllers": eec_config,
              "run": {k: v for k, v in vars(opts).items() if k != "overrides"} |
              {"eec": vars(settings), "feedback": feedback}}
    text = "\n".join(filter(None, [default_bench_config_text(), default_eec_config_text(),
                                   user_text]))
    session = Session(out, clock, base, kind="bench", config=merged, config_text=text)
    log = RunLog()
    try:
        kalman = BenchKalman(models, kalman_settings(eec_config)) if models else None
        decide = (make_eec(session, problem, models, settings, feedback, log)
                  if models is not None else make_bc(problem, settings.step_s, log))
        _run(session, opts, bench_config, problem, kalman, decide, divisor, log)
    except BaseException:
        session.close()
        raise
    kpis = kpis_of(log, problem, opts, settings, out)
    session.close(kpis=kpis)
    return kpis


def _run(session: Session, opts: BenchRunOptions, bench_config: dict[str, Any],
         problem: BenchProblem, kalman: BenchKalman | None, decide: Decide, divisor: int,
         log: RunLog) -> None:
    clock = session.clock
    rig = None
    try:
        rig = attach_bench(session, bench_config, opts.bench, play_sequence=False,
                           seed=opts.seed, disturbance=opts.disturbance or None)
        player = SequencePlayer(rig.bench, rig.sequence, divisor=rig.sampler.divisor)

        def origin() -> int:
            return player.t0_ns if player.t0_ns is not None else clock.time_ns()

        session.add_task(Observer(rig, list(problem.peripherals), log, origin, kalman,
                                  problem.sequence.relays))
        session.add_task(player)
        session.add_task(ControllerTask(
            divisor, session.loop.base_period_ns, rig, problem, decide, origin, kalman,
            asynchronous=clock.mode == "realtime"))
        session.run(duration_s=opts.cycles * problem.sequence.period_s)
    finally:
        if rig is not None:
            rig.close()


def kalman_settings(eec_config: dict[str, Any]) -> KalmanSettings:
    k = eec_config.get("kalman", {})
    defaults = KalmanSettings()
    return KalmanSettings(*(lookup(k, name, float, getattr(defaults, name), source=SOURCE)
                            for name in ("model_sigma", "disturbance_sigma", "meter_sigma")))


def make_eec(session: Session, problem: BenchProblem, models: BenchModels,
             settings: EECSettings, feedback: bool, log: RunLog) -> Decide:
    eec = EEC(models, problem, settings, feedback=feedback)
    plan_topic = session.topic("/eec/plan", PLAN_SCHEMA)
    estimate_topic = session.topic("/eec/estimate", ESTIMATE_SCHEMA)
    names = list(problem.peripherals)

    def decide(d: DecisionInput) -> dict[str, bool]:
        t, t_ns = d.t_s, d.t_ns
        estimate = d.estimate
        assert estimate is not None
        estimate_topic.log(t_ns, {"disturbance_va": estimate.disturbance_va,
                                  "output_va": d.output_va, "innovation_va": d.innovation_va})
        decision = eec.step(Observation(t, d.levels, d.relays, estimate))
        if decision.solve is not None:
            log.solve_ms.append(decision.solve.solve_ms)
            log.solver_limits += decision.solve.status == "time_limit"
        for kind, message in decision.events:
            session.event(kind, message, level="warning", source="eec", t_s=t,
                          status=decision.solve.status if decision.solve else "")
            log.fallbacks += kind == "eec.fallback"
        plan = decision.plan
        if plan is not None:
            plan_topic.log(t_ns, {
                "t_s": plan.t_s, "status": plan.status, "solve_ms": plan.solve_ms,
                "objective": plan.objective, "peak_va": plan.peak_va,
                "energy_vas": plan.energy_vas, "rows": plan.rows,
                "u": {n: plan.u[j].tolist() for j, n in enumerate(names)},
                "q": {r.name: np.round(plan.q[j], 3).tolist()
                      for j, r in enumerate(problem.resources)},
                "power_va": np.round(plan.power_va, 2).tolist(),
            })
        return decision.relays

    return decide


def make_bc(problem: BenchProblem, step_s: float, log: RunLog) -> Decide:
    bc = BasicController(problem, step_s)

    def decide(d: DecisionInput) -> dict[str, bool]:
        t0 = time.perf_counter()
        command = bc.step(d.t_s, d.levels, d.relays)
        log.solve_ms.append((time.perf_counter() - t0) * 1e3)
        return command

    return decide


def kpis_of(log: RunLog, problem: BenchProblem, opts: BenchRunOptions, settings: EECSettings,
            out: str) -> dict[str, Any]:
    if not log.t or not log.levels_t:
        raise ConfigError("the run recorded no meter or level samples: nothing to evaluate")
    kpis = bench_kpis(
        problem, t_s=np.array(log.t), s_va=np.array(log.s),
        relays={n: np.array(v) for n, v in log.relays.items()},
        relays_t_s=np.array(log.relays_t),
        levels={n: np.array(v) for n, v in log.levels.items()},
        levels_t_s=np.array(log.levels_t), cycles=opts.cycles, limit_va=settings.limit_va,
    )
    return {"controller": opts.controller, "cycles": opts.cycles, **kpis,
            "solve_ms": timing_summary(log.solve_ms), "solves_at_limit": log.solver_limits,
            "fallbacks": log.fallbacks, "mcap": out}

