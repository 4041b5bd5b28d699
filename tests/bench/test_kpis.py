"""The streaming bench KPIs (:class:`hil.bench.kpis.BenchKpis`) give the same values as
the whole-run formulas they replaced, on a recorded session and on edge cases, in constant
memory."""

from __future__ import annotations

import tracemalloc
from dataclasses import replace

import numpy as np
import pytest

from hil.bench.config import load_configs
from hil.bench.kpis import BenchKpis, transitions
from hil.bench.run import BenchRunOptions, run_bench
from hil.core.recording.reader import read_session

pytestmark = pytest.mark.timeout(60)


# -- the whole-run formulas of the KPIs as they were before they streamed (the oracle) ----------
def reference_kpis(problem, t_s, s_va, relays, relays_t_s, levels, cycles, limit_va,
                   sample_period_s, dwell_tol_s=0.005):
    dt = np.diff(t_s, append=t_s[-1] + (t_s[-1] - t_s[-2] if t_s.size > 1 else 0.0))
    energy = float(np.sum(s_va * dt))
    names = problem.peripherals
    on = {n: np.asarray(relays[n]).astype(bool) for n in names}
    rdt = np.diff(relays_t_s, append=relays_t_s[-1] + (relays_t_s[-1] - relays_t_s[-2]
                                                       if relays_t_s.size > 1 else 0.0))
    both = np.logical_and.reduce([on[n] for n in names])
    n = max(1, round(1.0 / sample_period_s))
    c = np.concatenate([[0.0], np.cumsum(s_va)])
    peak = float(np.max((c[n:] - c[:-n]) / n)) if s_va.size >= n else float(s_va.mean())

    def dwell_violations(name):
        changes = relays_t_s[transitions(on[name])]
        return int(np.sum(np.diff(changes) < problem.dwell_s[name] - dwell_tol_s))

    def excursions(q, low, high):
        outside = (q < low) | (q > high)
        return int(outside[0]) + int(np.sum(outside[1:] & ~outside[:-1]))

    hours = max(float(relays_t_s[-1] - relays_t_s[0]), 1e-9) / 3600.0
    return {
        "J1_VA": round(energy, 1), "J2_VA": round(float(s_va.max()), 2),
        "SEC_VA": round(energy / cycles, 1), "peak_VA": round(peak, 2),
        "energy_VAs": round(energy, 1), "overlap_s": round(float(np.sum(rdt[both])), 2),
        "dwell_violations": sum(dwell_violations(n) for n in names),
        "level_violations": sum(excursions(np.asarray(levels[r.name]), r.q_min, r.q_max)
                                for r in problem.resources),
        "switches": {n: int(transitions(on[n]).size + int(on[n][0])) for n in names},
        "starts_per_hour": {n: round((int(np.sum(on[n][1:] & ~on[n][:-1])) + int(on[n][0]))
                                     / hours, 1) for n in names},
        "over_limit_s": round(float(np.sum(dt[s_va > limit_va])), 2),
    }


def streamed(problem, t_s, s_va, relays, relays_t_s, levels, levels_t_s, cycles, limit_va,
             sample_period_s):
    kpis = BenchKpis(problem, sample_period_s=sample_period_s, limit_va=limit_va)
    for t, s in zip(t_s, s_va, strict=True):
        kpis.power(float(t), float(s))
    for i, t in enumerate(relays_t_s):
        kpis.relays(float(t), {n: bool(relays[n][i]) for n in problem.peripherals})
    for i, t in enumerate(levels_t_s):
        kpis.levels(float(t), {name: float(v[i]) for name, v in levels.items()})
    return kpis.kpis(cycles).document()


@pytest.fixture(scope="module")
def problem():
    return load_configs()[0].problem


@pytest.mark.slow
def test_recorded_session_gives_the_whole_run_values(tmp_path, problem):
    out = str(tmp_path / "bc.mcap")
    run_bench(BenchRunOptions(controller="bc", cycles=1, out=out))
    data = read_session(out)
    power, relays, levels = (data.arrays(f"/bench/{name}")
                             for name in ("power", "relays", "levels"))
    t0 = power["log_time_ns"][0]
    t_s = (power["log_time_ns"] - t0) / 1e9
    relays_t = (relays["log_time_ns"] - t0) / 1e9
    levels_t = (levels["log_time_ns"] - t0) / 1e9
    s_va = np.asarray(power["total_va"], float)
    on = {n: np.asarray(relays[n]) for n in problem.peripherals}
    q = {r.name: np.asarray(levels[r.name], float) for r in problem.resources}
    limit = float(np.percentile(s_va, 80))  # some time above it
    expected = reference_kpis(problem, t_s, s_va, on, relays_t, q, 1, limit, 0.01)
    got = streamed(problem, t_s, s_va, on, relays_t, q, levels_t, 1, limit, 0.01)
    assert got == expected
    assert expected["overlap_s"] > 0 and expected["over_limit_s"] > 0
    assert sum(expected["switches"].values()) >= 3


def test_dwell_level_and_short_run_edge_cases(problem):
    problem = replace(problem, dwell_s=dict.fromkeys(problem.peripherals, 5.0))
    names = problem.peripherals
    t = np.arange(50) * 0.01  # shorter than the one-second window: peak is the mean
    s = np.linspace(100.0, 600.0, 50)
    relays = {names[0]: (np.arange(50) // 10) % 2 == 0,  # changes every 0.1 s: dwell violations
              names[1]: np.arange(50) >= 25}
    low, high = problem.resources[0].q_min, problem.resources[0].q_max
    q = {problem.resources[0].name: np.where(np.arange(50) % 20 < 5, low - 1, high - 1),
         problem.resources[1].name: np.full(50, problem.resources[1].q_max + 1)}
    expected = reference_kpis(problem, t, s, relays, t, q, 2, 400.0, 0.01)
    assert streamed(problem, t, s, relays, t, q, t, 2, 400.0, 0.01) == expected
    assert expected["dwell_violations"] >= 3 and expected["level_violations"] == 4


@pytest.mark.slow
def test_accumulators_do_not_grow_with_samples(problem):
    kpis = BenchKpis(problem, sample_period_s=0.01, limit_va=500.0)
    names = problem.peripherals
    levels = {r.name: (r.q_min + r.q_max) / 2 for r in problem.resources}

    def feed(first: int, count: int) -> None:
        for k in range(first, first + count):
            t = k * 0.01
            kpis.power(t, 300.0 + (k % 70))
            kpis.relays(t, {n: (k // (700 + 100 * j)) % 2 == 0 for j, n in enumerate(names)})
            kpis.levels(t, levels)

    feed(0, 2000)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        feed(2000, 30_000)
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert kpis.power_samples == 32_000
    assert grown < 4096, f"the KPI accumulators grew by {grown} B over 30,000 samples"
