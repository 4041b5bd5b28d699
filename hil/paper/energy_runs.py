"""The energy paper's runs: every bench run of its tables, figures and J1 sensitivity study as
one sweep on hil's sweep engine (:mod:`hil.sweep`), and its three identification experiments.

Every run is ``hil bench run`` under the paper's conditions (``hil/configs/paper_energy.toml``)
with a few flags of its own: the trials of one sweep whose parameters include the controller.
A condition the flags cannot set (the levels' range, the unexpected load's size and timing) is
a config file of its own, the paper's with that one change, written beside the sessions.
"""

from __future__ import annotations

import importlib.resources
import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from hil.bench.identify_options import IdentifyOptions
from hil.controllers.base import BenchObservation
from hil.controllers.bench.bc import BasicController
from hil.controllers.bench.problem import BenchProblem
from hil.controllers.ident.n4sid import IdentifiedModel
from hil.core.config import deep_merge, load_toml
from hil.sweep.engine import Engine, RayMissingError, import_ray
from hil.sweep.space import Trial
from hil.sweep.sweep import Sweep, check_trials, run_sweep

T_S = 28                       # the machine cycle T [s] (paper_energy.toml's sequence)
PAPER_CYCLES = 8               # T_S = 8 T (section V-D)
QUICK_CYCLES = 1


def paper_config() -> Path:
    """The paper's conditions, packaged with hil."""
    return Path(str(importlib.resources.files("hil.configs").joinpath("paper_energy.toml")))


@dataclass(frozen=True)
class Knob:
    """One condition the J1 sensitivity study moves: its values (``quick``: those of a quick
    run), the paper's (or hil's choice where the paper is silent), and which controllers
    each value is run with (the other keeps its baseline run)."""

    key: str
    label: str
    baseline: Any
    values: tuple[Any, ...]
    quick: tuple[Any, ...]
    controllers: tuple[str, ...]


KNOBS = (
    Knob("band", "BC's hysteresis band (share of the range it fills)", 1.0,
         (0.25, 0.5, 0.75), (), ("bc",)),
    Knob("range", "levels' range, x Table I's (BC's T_P grows with it)", 1.0,
         (0.5, 0.75, 1.5), (), ("bc", "eec")),
    Knob("load", "unexpected load [VA]", 0.0, (70.0, 180.0, 270.0), (180.0,),
         ("bc", "eec")),
    Knob("shift", "unexpected load's windows shifted by [s] (180 VA)", 0.0,
         (7.0, 14.0, 21.0), (), ("bc", "eec")),
    Knob("hp", "prediction horizon H_p [s]", T_S, (14, 42, 56, "T_P"), (42, 56, "T_P"),
         ("eec",)),
    Knob("gamma", "weights gamma1 / gamma2", (0.9, 0.1),
         ((1.0, 0.0), (0.7, 0.3), (0.5, 0.5), (0.3, 0.7)), (), ("eec",)),
    Knob("terminal", "EEC's terminal condition (hil's default: hold)", "none", ("hold",), (),
         ("eec",)),
)


#: the runs of the tables and figures, by name (H_S = T is --hs 28; "eec" and "bc" are the
#: baselines of the sensitivity study; hp = "T_P" is BC's peripheral cycle)
BASE_RUNS: dict[str, dict[str, Any]] = {
    "bc": {"controller": "bc"},
    "eec-hs1": {"controller": "eec", "hs": 1},
    "eec": {"controller": "eec", "hs": T_S},
    "eec-hp42": {"controller": "eec", "hp": 42, "hs": T_S},
    "eec-hp56": {"controller": "eec", "hp": 56, "hs": T_S},
    "eec-hpTP": {"controller": "eec", "hp": "T_P", "hs": T_S},
    "bc-dist": {"controller": "bc", "disturbance": True},
    "eec-dist": {"controller": "eec", "hs": T_S, "disturbance": True},
}


@dataclass
class RunPlan:
    """What a reproduction runs: the bench runs (name -> their flags beyond the paper's
    conditions), which run stands for each point of the sensitivity study ((knob, value,
    controller) -> name), the cycles of every run, ``tp_s`` (BC's peripheral cycle T_P [s])
    and the length of each identification experiment [s]."""

    runs: dict[str, dict[str, Any]]
    points: dict[tuple[str, Any, str], str]
    cycles: int
    tp_s: int
    ident_s: float
    quick: bool

    @property
    def ident_block_rows(self) -> int | None:
        """The Hankel block rows of the identifications: chosen by BIC as ``hil identify``
        does, or 15 in a quick run (a tenth of the time)."""
        return 15 if self.quick else None

    def point(self, knob: str, value: Any, controller: str) -> str:
        """The run of ``controller`` with ``knob`` at ``value`` (its nominal baseline run
        when the knob does not move that controller)."""
        return self.points.get((knob, value, controller), controller)


def plan_runs(quick: bool, problem: BenchProblem, configs: Path) -> RunPlan:
    """Every bench run of the report; variant configs are written into ``configs``. A knob's
    run that is a run of the tables already (the same flags) is not run twice."""
    tp_s = round(max(bc_cycle_s(problem).values()))
    runs = {name: {k: tp_s if v == "T_P" else v for k, v in params.items()}
            for name, params in BASE_RUNS.items()}
    points = {}
    for knob in KNOBS:
        for value in (knob.baseline, *(knob.quick if quick else knob.values)):
            for controller in knob.controllers:
                params = knob_params(knob, value, controller, tp_s, configs)
                name = next((n for n, p in runs.items() if p == params),
                            f"{controller}-{knob.key}-{_name(value)}")
                runs.setdefault(name, params)
                points[knob.key, value, controller] = name
    return RunPlan(runs, points, QUICK_CYCLES if quick else PAPER_CYCLES, tp_s,
                   40.0 if quick else 600.0, quick)


def knob_values(knob: Knob, quick: bool) -> tuple[Any, ...]:
    """The knob's values in this reproduction, its baseline among them, in order."""
    values = (knob.baseline, *(knob.quick if quick else knob.values))
    if knob.key == "gamma":
        return tuple(sorted(values, reverse=True))
    if knob.key == "terminal":
        return values
    return tuple(sorted(values, key=lambda v: math.inf if v == "T_P" else float(v)))


def knob_params(knob: Knob, value: Any, controller: str, tp_s: int, configs: Path
                ) -> dict[str, Any]:
    """The flags of ``controller``'s run with ``knob`` at ``value``, everything else the
    baseline's (BC; the EEC with H_S = T; for the load's timing, both with the load on)."""
    base: dict[str, Any] = {"controller": controller} | ({"hs": T_S} if controller == "eec"
                                                          else {})
    key = knob.key
    if key == "shift":
        base["disturbance"] = True
    if value == knob.baseline:
        return base
    if key == "band":
        return base | {"param.band": value}
    if key == "hp":
        hp = tp_s if value == "T_P" else int(value)
        return base | {"hp": hp, "hs": min(T_S, hp)}
    if key == "gamma":
        return base | {"gamma1": value[0], "gamma2": value[1]}
    if key == "terminal":
        return base | {"terminal": value}
    if key == "range":
        change = range_change(value)
    elif key == "load":
        base["disturbance"] = True
        if value == paper_load()["va"]:
            return base
        change = {"plant": {"disturbance": {"va": value}}}
    else:  # shift
        change = shift_change(value)
    return base | {"config": str(variant_config(configs, f"{key}-{_name(value)}", change))}


def _name(value: Any) -> str:
    text = "-".join(f"{v:g}" for v in value) if isinstance(value, tuple) else (
        f"{value:g}" if isinstance(value, float) else str(value))
    return re.sub(r"[^A-Za-z0-9.]+", "-", text)


def paper_load() -> dict[str, Any]:
    """The unexpected load of the paper's config (``[plant.disturbance]``)."""
    data, _ = load_toml(paper_config())
    return dict(data["plant"]["disturbance"])


def range_change(scale: float) -> dict[str, Any]:
    """Table I's operating ranges scaled by ``scale`` from their bottom."""
    bounds = {"q1": (50.0, 150.0), "q2": (60.0, 180.0)}
    return {"plant": {"resources": {name: {"bounds": [low, low + scale * (high - low)]}
                                    for name, (low, high) in bounds.items()}}}


def shift_change(shift_s: float) -> dict[str, Any]:
    """The unexpected load's windows (paper_energy.toml) ``shift_s`` later, wrapped into its
    period."""
    load = paper_load()
    period = float(load["period_s"])
    windows: list[list[float]] = []
    for start, end in load["windows"]:
        start, end = start + shift_s, end + shift_s
        if end <= period:
            windows.append([start, end])
        elif start >= period:
            windows.append([start - period, end - period])
        else:
            windows += [[start, period], [0.0, end - period]]
    return {"plant": {"disturbance": {"windows": sorted(windows)}}}


def variant_config(folder: Path, name: str, change: Mapping[str, Any]) -> Path:
    """The paper's config with ``change`` laid over it, written to ``folder/NAME.toml``."""
    data, _ = load_toml(paper_config())
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.toml"
    path.write_text(f"# the paper's conditions ({paper_config().name}) with one change\n"
                    + tomli_w.dumps(deep_merge(data, change)), encoding="utf-8")
    return path


def bc_cycle_s(problem: BenchProblem, band: float = 1.0, cycles: int = 40) -> dict[str, float]:
    """BC's operational cycle T_P of each peripheral [s]: the mean time between its starts,
    from BC closed on eq. (10) alone (the emulator's levels follow it exactly)."""
    bc = BasicController(problem, band=band)
    levels = {r.name: r.q0 for r in problem.resources}
    relays = dict.fromkeys(problem.peripherals, False)
    starts: dict[str, list[int]] = {name: [] for name in problem.peripherals}
    for t in range(int(cycles * problem.sequence.period_s)):
        command = bc.decide(BenchObservation(float(t), levels, relays, 0.0))
        for name, on in command.items():
            if on and not relays[name]:
                starts[name].append(t)
        relays = command
        for r in problem.resources:
            used = problem.sequence.on_fraction(r.consumer, t, t + 1)
            levels[r.name] += r.alpha * used + r.eta * relays[r.supplier]
    return {name: float((times[-1] - times[1]) / (len(times) - 2)) if len(times) > 2
            else math.inf for name, times in starts.items()}


def bench_sweep(plan: RunPlan, folder: Path, quick: bool) -> Sweep:
    """The runs of ``plan`` as one sweep into ``folder``: on Ray (one worker per core, at most
    2) when it is installed, else one after another in this process; a quick run always so."""
    base = {"cycles": plan.cycles, "config": str(paper_config()), "quiet": True}
    trials = tuple(Trial(name, dict(params)) for name, params in plan.runs.items())
    keys = tuple(dict.fromkeys(key for params in plan.runs.values() for key in params))
    return Sweep("bench", base, keys, trials, folder, engine_for(quick))


def engine_for(quick: bool) -> Engine:
    if quick:
        return Engine(serial=True)
    try:
        import_ray()
    except RayMissingError:
        return Engine(serial=True)
    return Engine(workers=min(2, os.cpu_count() or 1))


@dataclass(frozen=True)
class SweepRows:
    """The rows of the runs by name (``hil sweep``'s: params, kpis, mcap, status...) and how
    the sweep ran (engine, workers, wall_s, csv)."""

    rows: dict[str, dict[str, Any]]
    engine: str
    workers: int
    wall_s: float
    csv: str


def run_bench_sweep(sweep: Sweep, stream: Any) -> SweepRows:
    """Run every trial (each planned first, as ``hil sweep`` does)."""
    check_trials(sweep)
    result = run_sweep(sweep, stream)
    return SweepRows({trial["name"]: trial for trial in result["trials"]}, result["engine"],
                     result["workers"], result["wall_s"], result["csv"])


# -- N4SID -------------------------------------------------------------------------------------

#: the paper's three models: relays switched by PRBS, the machining mode, PRBS seed (as
#: hil/configs/models/regenerate.sh makes hil's)
IDENTIFICATIONS = {"P1": (("P1",), "off", 1), "P2": (("P2",), "off", 2),
                   "machining": ((), "prbs", 3)}
OUTPUT = "/bench/power:va_l2"


@dataclass(frozen=True)
class Identified:
    """One identification: its model, the session, and the record it was fitted on."""

    name: str
    model: IdentifiedModel
    mcap: str
    t_s: np.ndarray
    u: np.ndarray          # samples x inputs
    y: np.ndarray          # samples


def identify_load(name: str, duration_s: float, folder: Path,
                  block_rows: int | None = None) -> Identified:
    """``hil bench identify`` + ``hil identify --order 3 --detrend --no-feedthrough`` of one
    of the paper's models, under the paper's conditions."""
    from hil.bench.identify import run_identify_experiment
    from hil.controllers.ident.n4sid import identify
    from hil.core.identify import aligned_signals, parse_signal, save_model_file
    from hil.core.recording.reader import read_session

    relays, machining, seed = IDENTIFICATIONS[name]
    folder.mkdir(parents=True, exist_ok=True)
    mcap = str(folder / f"ident-{name}.mcap")
    run_identify_experiment(IdentifyOptions(
        relays=relays, duration_s=duration_s, seed=seed, machining=machining, out=mcap,
        config_path=str(paper_config()), progress_s=0.0))
    switched = relays or ("M1", "M2")
    inputs = [parse_signal(f"/ident/relays:{relay}{suffix}")
              for relay in switched for suffix in ("", "_start")]
    u, y, dt, _irregular = aligned_signals(read_session(mcap), inputs, [parse_signal(OUTPUT)])
    model = identify(u, y, dt, inputs=tuple(s.text for s in inputs), outputs=(OUTPUT,),
                     order=3, detrend=True, feedthrough=False, block_rows=block_rows)
    save_model_file(folder / f"ident-{name}.json", model)
    return Identified(name, model, mcap, np.arange(len(y)) * dt, u, np.asarray(y)[:, 0])
