"""``hil bench run``: EEC or BC closed-loop against the relay bench, recorded to MCAP.

Loop (base period 0.01 s, tasks in this order every tick):

1. [lockstep emulator] plant step, 2. sampler (meter and levels, safety service; publishes
   ``/bench/power``, ``/bench/levels``, ``/bench/relays``) - both from :func:`attach_bench`;
3. ``estimator`` (100 Hz): logs the sample for the KPIs and feeds the controller's estimator
   (the EEC's Kalman filter) the relays held during the last step and this reading;
4. ``sequence``: the machining sequence player (M1/M2);
5. ``controller`` (every 100 ticks = 1 s): EEC or BC decides P1/P2 through the safety layer;
   the EEC's plan goes to ``/eec/plan``, fallbacks and solver trouble to ``/events``.

Tasks 3 and 5 are :mod:`hil.bench.control`'s. KPIs (:mod:`controllers.bench_kpis`) are
computed from the samples the loop saw and stored in the session (``hil report`` prints them).
"""

from __future__ import annotations

import importlib.resources
import os
import tempfile
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from controllers.base import BenchController
from controllers.bc import BasicController
from controllers.bench_kpis import bench_kpis, timing_summary
from controllers.bench_models import DeviceModel, MachiningModel, load_linear_model
from controllers.bench_problem import BenchProblem
from controllers.eec import EEC, EECSettings
from controllers.eec_prediction import BenchModels
from hil.bench.config import BenchConfig, EecConfig, EecTable, default_text, load_configs
from hil.bench.control import (
    ControllerTask,
    Observer,
    RecordedEEC,
    RunLog,
    TimedController,
    estimator_of,
)
from hil.bench.rig import SequencePlayer, attach_bench, is_emulated, session_clock
from hil.core.errors import ConfigError, UsageError
from hil.core.session import Session
from hil.core.types import TimeSource

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



class SequenceOrigin:
    """Clock time of the machining sequence's start, which every ``t_s`` counts from: the
    player's first tick (the clock's time until then)."""

    def __init__(self, clock: TimeSource) -> None:
        self.clock = clock
        self.player: SequencePlayer | None = None

    def __call__(self) -> int:
        t0 = self.player.t0_ns if self.player is not None else None
        return t0 if t0 is not None else self.clock.time_ns()


def model_path(name: str, eec: EecConfig, key: str) -> str:
    """A model file: absolute, relative to the working directory, or next to eec.toml."""
    if os.path.isabs(name) or os.path.exists(name):
        return name
    packaged = importlib.resources.files("hil.configs").joinpath(name)
    if packaged.is_file():
        return str(packaged)
    raise ConfigError(f"{eec.source}: key '{key}': model file {name!r} not found (working "
                      "directory or hil/configs)")


def load_models(eec: EecConfig, problem: BenchProblem) -> BenchModels:
    """The EEC's load models from the files ``[models]`` names."""
    machining = load_linear_model(
        model_path(eec.models["machining"], eec, "models.machining"), "machining")
    devices = {}
    for name in problem.peripherals:
        path = model_path(eec.models[name], eec, f"models.{name}")
        devices[name] = DeviceModel.from_linear(load_linear_model(path, name))
    models = BenchModels(MachiningModel.from_linear(machining, problem.sequence), devices)
    dts = {machining.dt, *(d.dt for d in devices.values())}
    if len(dts) != 1:
        raise ConfigError(f"{eec.source}: every model must have the same dt, got {sorted(dts)}")
    return models


def eec_settings(table: EecTable, opts: BenchRunOptions) -> EECSettings:
    """The EEC's settings: ``[eec]`` with the command line's flags laid over it."""
    step = table.step_s
    hp = opts.hp_s if opts.hp_s is not None else table.hp_s
    hs = opts.hs_s if opts.hs_s is not None else table.hs_s
    try:
        return EECSettings(
            hp_steps=round(hp / step), hs_steps=round(hs / step), step_s=step,
            gamma1=opts.gamma1 if opts.gamma1 is not None else table.gamma1,
            gamma2=opts.gamma2 if opts.gamma2 is not None else table.gamma2,
            terminal=table.terminal, limit_va=table.limit_va,
            limit_weight=table.limit_weight, peak_resolution_va=table.peak_resolution_va,
            time_limit_s=table.time_limit_s, mip_rel_gap=table.mip_rel_gap,
        )
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def run_bench(opts: BenchRunOptions) -> dict[str, Any]:
    """Run one closed-loop bench session; return the KPI dictionary (``hil bench run``)."""
    if opts.controller not in CONTROLLERS:
        raise UsageError(f"controller must be one of {CONTROLLERS}, got {opts.controller!r}")
    if opts.disturbance and not is_emulated(opts.bench):
        raise UsageError("--disturbance switches the emulator's unknown load on: it needs "
                         "--bench emulated")
    bench, eec = load_configs(opts.config_path, opts.overrides)
    bench = bench.with_dwell(opts.dwell_s)  # the safety layer enforces the controllers' dwell
    problem = bench.problem
    settings = eec_settings(eec.eec, opts)
    out = opts.out or os.path.join(tempfile.gettempdir(),
                                   f"hil-bench-{opts.controller}-{int(time.time())}.mcap")
    models = load_models(eec, problem) if opts.controller == "eec" else None
    clock = session_clock(opts.bench, opts.realtime)
    merged = {"bench": bench.data, "controllers": eec.data,
              "run": {k: v for k, v in vars(opts).items() if k != "overrides"} |
              {"eec": vars(settings), "feedback": eec.eec.feedback}}
    text = "\n".join(filter(None, [default_text("bench.toml"), default_text("eec.toml"),
                                   bench.user_text]))
    session = Session(out, clock, bench.sampling.period_s, kind="bench", config=merged,
                      config_text=text)
    log = RunLog()
    origin = SequenceOrigin(clock)
    try:
        controller: BenchController
        if models is not None:
            controller = RecordedEEC(EEC(models, problem, settings, feedback=eec.eec.feedback,
                                         kalman=eec.kalman), session, problem, log, origin)
        else:
            controller = TimedController(BasicController(problem, settings.step_s), log)
        _run(session, opts, bench, controller, settings.step_s, log, origin)
    except BaseException:
        session.close()
        raise
    kpis = kpis_of(log, problem, opts, settings, out)
    session.close(kpis=kpis)
    return kpis


def _run(session: Session, opts: BenchRunOptions, bench: BenchConfig,
         controller: BenchController, step_s: float, log: RunLog, origin: SequenceOrigin
         ) -> None:
    rig = None
    try:
        rig = attach_bench(session, bench, opts.bench, play_sequence=False,
                           seed=opts.seed, disturbance=opts.disturbance or None)
        player = origin.player = SequencePlayer(rig.bench, rig.sequence,
                                                divisor=rig.sampler.divisor)
        problem = bench.problem
        session.add_task(Observer(rig, list(problem.peripherals), log, origin,
                                  estimator_of(controller)))
        session.add_task(player)
        session.add_task(ControllerTask(
            round(step_s / bench.sampling.period_s), session.loop.base_period_ns, rig,
            problem.peripherals, controller, origin,
            asynchronous=session.clock.mode == "realtime"))
        session.run(duration_s=opts.cycles * problem.sequence.period_s)
    finally:
        if rig is not None:
            rig.close()


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

