"""What the energy paper's report measures in hil's sessions: the signals of a bench run, its
J1, J2 and SEC over any window from its start (a run's first cycles are the run of that
length: lockstep, and no controller knows when the run ends), and where a J1 difference
between two runs goes.

Where J1 goes. The machining sequence is the same in every run, and a peripheral's resource
follows eq. (10) with nothing lost, so over a window a peripheral is on exactly as long as it
takes to deliver what the machining consumed plus what its level gained. J1 of two runs then
differs by (a) the resource left in the tanks at the window's end, each unit worth
``S_Pj / eta_j`` VA s (``S_Pj`` the peripheral's steady apparent power), (b) the inrush of the
starts one run made more than the other, measured on the plant, and (c) the rest: noise, the
unexpected load, a start while the motor still coasts.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil.bench.config import BenchConfig
from hil.bench.report import session_config
from hil.core.recording.reader import read_session

INRUSH_WINDOW_S = 5.0   # a start's inrush is over well within the dwell (0.4-0.5 s)


@dataclass(frozen=True)
class RunSignals:
    """A bench session's signals, time in s from its first meter sample."""

    t: np.ndarray                       # meter samples
    va: np.ndarray                      # total apparent power [VA]
    relay_t: np.ndarray
    relays: dict[str, np.ndarray]       # 0/1 per relay
    level_t: np.ndarray
    levels: dict[str, np.ndarray]
    plan_t: np.ndarray                  # the EEC's decisions (empty for BC)
    solve_ms: np.ndarray
    estimate_t: np.ndarray              # the EEC's Kalman filter at its decisions
    disturbance_va: np.ndarray          # its estimate of the unknown load
    config: dict[str, Any]              # the run's configuration as recorded


def read_signals(mcap: str) -> RunSignals:
    """The signals of the session ``mcap``."""
    data = read_session(mcap)
    power = data.arrays("/bench/power")
    t0 = int(power["log_time_ns"][0])

    def seconds(stamps: np.ndarray) -> np.ndarray:
        return (np.asarray(stamps, dtype=np.int64) - t0) / 1e9

    relays = data.arrays("/bench/relays")
    levels = data.arrays("/bench/levels")
    plans = [(t, m) for t, m in data.topic("/eec/plan") if isinstance(m, dict)]
    estimates = data.arrays("/eec/estimate")
    return RunSignals(
        seconds(power["log_time_ns"]), power["total_va"].astype(float),
        seconds(relays["log_time_ns"]),
        {name: relays[name].astype(float) for name in ("M1", "M2", "P1", "P2")},
        seconds(levels["log_time_ns"]),
        {name: levels[name].astype(float) for name in levels if name != "log_time_ns"},
        seconds(np.array([t for t, _ in plans], dtype=np.int64)),
        np.array([float(m.get("solve_ms", np.nan)) for _, m in plans]),
        seconds(estimates["log_time_ns"]),
        estimates.get("disturbance_va", np.zeros(0)).astype(float),
        session_config(data))


@dataclass(frozen=True)
class Window:
    """A run's paper figures over ``[0, end_s)``: J1 [VA s], J2 [VA], SEC [VA s per cycle],
    and per peripheral its starts, time on [s] and level change."""

    end_s: float
    cycles: float
    j1: float
    j2: float
    starts: dict[str, int]
    on_s: dict[str, float]
    level_gain: dict[str, float]       # q_j(end) - q_j(0)
    solve_ms: np.ndarray

    @property
    def sec(self) -> float:
        return self.j1 / self.cycles


def window(signals: RunSignals, cycles: float, cycle_s: float,
           peripherals: Mapping[str, str]) -> Window:
    """The figures of the run's first ``cycles`` machine cycles; ``peripherals`` maps each
    peripheral to its resource. J1 sums every sample held until the next (the last as long
    as the one before it), as the run's own KPI does."""
    end = cycles * cycle_s
    t, va = signals.t, signals.va
    held = np.diff(t, append=t[-1] + (t[-1] - t[-2]))
    inside = t < end - 1e-9
    rt, lt = signals.relay_t, signals.level_t
    r_in, l_in = rt < end - 1e-9, lt < end - 1e-9
    r_held = np.diff(rt, append=rt[-1] + (rt[-1] - rt[-2]))
    starts, on_s, gain = {}, {}, {}
    for name, resource in peripherals.items():
        on = signals.relays[name][r_in]
        starts[name] = int(np.count_nonzero(np.diff(np.concatenate([[0.0], on])) > 0.5))
        on_s[name] = float(np.sum(on * r_held[r_in]))
        level = signals.levels[resource][l_in]
        gain[name] = float(level[-1] - level[0])
    solved = signals.plan_t < end - 1e-9
    return Window(end, cycles, float(np.sum(va[inside] * held[inside])),
                  float(np.max(va[inside])), starts, on_s, gain, signals.solve_ms[solved])


@dataclass(frozen=True)
class Peripheral:
    """What one start and one unit of resource cost, measured on the emulated plant:
    ``steady_va`` (S_Pj), ``inrush_vas`` (the energy of a start from rest beyond the steady
    draw, over its first INRUSH_WINDOW_S), ``eta`` (resource per second on)."""

    name: str
    resource: str
    steady_va: float
    inrush_vas: float
    eta: float

    @property
    def vas_per_unit(self) -> float:
        """VA s of one unit of resource delivered."""
        return self.steady_va / self.eta


def measure_peripherals(config: BenchConfig) -> dict[str, Peripheral]:
    """Each peripheral switched on alone from rest on a fresh plant (noise-free loads)."""
    from hil.emulators.bench.plant import BenchPlant

    out = {}
    for resource in config.problem.resources:
        name = resource.supplier
        plant = BenchPlant(config.plant)
        plant.set_relay(name, True)
        steps = round(INRUSH_WINDOW_S / plant.dt)
        va = np.empty(2 * steps)
        for k in range(va.size):
            plant.step()
            va[k] = plant.load_va()[name]
        steady = float(np.mean(va[steps:]))
        out[name] = Peripheral(name, resource.name, steady,
                               float(np.sum(va[:steps] - steady) * plant.dt), resource.eta)
    return out


@dataclass(frozen=True)
class J1Split:
    """``ours`` against ``baseline``: J1 saved [VA s] and where it comes from (the baseline's
    figure less ours in each): the resource left in the tanks, the starts' inrush, the rest."""

    saved: float
    stored: float
    starts: float

    @property
    def rest(self) -> float:
        return self.saved - self.stored - self.starts


def split_j1(ours: Window, baseline: Window, peripherals: Mapping[str, Peripheral]) -> J1Split:
    stored = sum(p.vas_per_unit * (baseline.level_gain[n] - ours.level_gain[n])
                 for n, p in peripherals.items())
    starts = sum(p.inrush_vas * (baseline.starts[n] - ours.starts[n])
                 for n, p in peripherals.items())
    return J1Split(baseline.j1 - ours.j1, stored, starts)


def level_adjusted_j1(run: Window, peripherals: Mapping[str, Peripheral]) -> float:
    """J1 had the run left every level where it found it: J1 less the resource it stored."""
    return run.j1 - sum(p.vas_per_unit * run.level_gain[n] for n, p in peripherals.items())


def cycle_times(signals: RunSignals, name: str) -> np.ndarray:
    """The times between a peripheral's starts in the run [s] (BC's T_P, measured)."""
    on = signals.relays[name]
    starts = signals.relay_t[1:][np.diff(on) > 0.5]
    return np.diff(starts)


class MissingRunError(LookupError):
    """A run the report needs did not complete (its trial failed); the message says why."""


class RunSessions:
    """The sessions of a reproduction's runs by name (``hil sweep``'s rows), read once each;
    ``cycle_s`` the machine cycle, ``peripherals`` each peripheral's resource."""

    def __init__(self, rows: Mapping[str, Mapping[str, Any]], cycle_s: float,
                 peripherals: Mapping[str, str]) -> None:
        self.rows, self.cycle_s, self.peripherals = rows, cycle_s, peripherals
        self._signals: dict[str, RunSignals] = {}

    def signals(self, name: str) -> RunSignals:
        row = self.rows.get(name)
        if row is None or row.get("status") != "ok":
            why = "not run" if row is None else row.get("error") or row.get("run_status")
            raise MissingRunError(f"run {name} did not complete ({why})")
        if name not in self._signals:
            self._signals[name] = read_signals(str(row["mcap"]))
        return self._signals[name]

    def window(self, name: str, cycles: float) -> Window:
        """The figures of run ``name`` over its first ``cycles`` machine cycles."""
        return window(self.signals(name), cycles, self.cycle_s, self.peripherals)
