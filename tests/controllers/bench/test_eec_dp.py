"""The schedule DP (hil.controllers.bench.eec_dp) against the exact MILP on recorded decision
instants.

``tests/data/eec_instants.npz``: twelve decision instants of a closed-loop run of the default
EEC (H_p = 28 s, emulated bench), among them the ones the MILP needed longest to prove.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import highspy
import numpy as np
import pytest

from hil.bench.builtin import eec_settings, load_models
from hil.bench.config import load_configs
from hil.controllers.bench.eec_repair import feasible
from hil.controllers.bench.eec_solver import HorizonSolver
from hil.controllers.bench.prediction import HorizonPrediction

DATA = Path(__file__).parents[2] / "data" / "eec_instants.npz"


@pytest.fixture(scope="module")
def setup():
    bench, eec = load_configs(None, {})
    problem = bench.problem
    settings = eec_settings(eec.eec)
    models = load_models(eec, problem)
    prediction = HorizonPrediction(models, problem, settings.hp_steps,
                                   round(settings.step_s / models.dt))
    data = np.load(DATA)
    instants = [(data[f"free{n}"], data[f"u_prev{n}"], data[f"fixed{n}"], data[f"q0{n}"],
                 float(data[f"t{n}"]), data[f"warm{n}"] if data[f"warm{n}"].size else None)
                for n in range(12)]
    return prediction, problem, settings, instants


def solvers(prediction, problem, settings, **changes):
    # the MILP runs HiGHS with threads = 1: a scheduler another test started with more
    # threads would make its run fail ("Not Set")
    highspy.Highs.resetGlobalScheduler(True)
    dp = HorizonSolver(prediction, problem, dataclasses.replace(settings, solver="dp",
                                                                time_limit_s=60.0, **changes))
    milp = HorizonSolver(prediction, problem, dataclasses.replace(
        settings, solver="milp", time_limit_s=60.0, mip_rel_gap=1e-9, **changes))
    return dp, milp


@pytest.mark.parametrize("gamma3", [0.0, 0.02])
@pytest.mark.slow
def test_dp_objective_equals_the_exact_milp(setup, gamma3):
    prediction, problem, settings, instants = setup
    dp, milp = solvers(prediction, problem, settings, gamma3=gamma3)
    for free, u_prev, fixed, q0, t_s, warm in instants:
        exact = milp.solve(free, u_prev, fixed, q0, t_s)
        for start in (None, warm):  # cold, and with the previous plan as the incumbent
            fast = dp.solve(free, u_prev, fixed, q0, t_s, start)
            assert exact.status == "optimal" and fast.status == "optimal"
            assert fast.gap == 0.0 and fast.bound == pytest.approx(fast.objective)
            assert fast.objective == pytest.approx(exact.objective, rel=1e-6)
            # the DP's plan is a plan of the MILP: the same cost when evaluated by it
            u = fast.u.astype(float)
            horizon = dp.horizon
            quick = horizon.costs(u, 0, u[:1], u_prev, horizon.peak_table(free))[0]
            assert quick == pytest.approx(fast.objective, rel=1e-9)
            assert feasible(horizon, u, u_prev, fixed, *bounds(horizon, q0, t_s))


def bounds(horizon, q0, t_s):
    lo, hi = horizon.level_bounds(q0, t_s)
    return np.maximum(lo, 0.0), np.minimum(hi, np.arange(horizon.H) + 1.0)


def switch_ons(u, u_prev):
    prev = np.concatenate([u_prev[:, None], u[:, :-1]], axis=1)
    return int(np.sum((u > 0.5) & (prev < 0.5)))


def test_switch_on_cost_reduces_starts(setup):
    prediction, problem, settings, instants = setup
    starts = []
    for gamma3 in (0.0, 0.02):
        dp, _ = solvers(prediction, problem, settings, gamma3=gamma3)
        starts.append(sum(switch_ons(dp.solve(free, u_prev, fixed, q0, t_s).u, u_prev)
                          for free, u_prev, fixed, q0, t_s, _ in instants))
    assert starts[1] < starts[0]


def test_gamma3_only_adds_its_cost_per_switch_on(setup):
    """gamma3 = 0 is the paper's J: the objective is w1 J1 + the peak cost, nothing else; a
    positive gamma3 adds gamma3 per switch-on of the same plan."""
    prediction, problem, settings, instants = setup
    paper, _ = solvers(prediction, problem, settings, gamma3=0.0)
    wear, _ = solvers(prediction, problem, settings, gamma3=0.05)
    for free, u_prev, fixed, q0, t_s, _ in instants:
        result = paper.solve(free, u_prev, fixed, q0, t_s)
        u = result.u.astype(float)
        prev = np.concatenate([u_prev[:, None], u[:, :-1]], axis=1)
        starts = np.clip(u - prev, 0, None)
        horizon = paper.horizon
        energy = sum(horizon.area_u[j] @ u[j] + horizon.area_s[j] @ starts[j] for j in range(2))
        assert result.objective == pytest.approx(
            horizon.w1 * energy + horizon.peak_cost(result.peak_va), rel=1e-9)
        table = wear.horizon.peak_table(free)
        assert wear.horizon.costs(u, 0, u[:1], u_prev, table)[0] == pytest.approx(
            result.objective + 0.05 * switch_ons(u, u_prev), rel=1e-9)


def test_budget_is_a_safety_net(setup):
    prediction, problem, settings, instants = setup
    dp = HorizonSolver(prediction, problem, dataclasses.replace(settings, time_limit_s=1e-9))
    free, u_prev, fixed, q0, t_s, warm = instants[2]
    result = dp.solve(free, u_prev, fixed, q0, t_s, warm)
    # out of time at once: the repaired previous plan is kept, not proven
    assert result.status == "time_limit" and result.u is not None
    # not proven: the gap is what is left between the plan and the bound
    assert result.gap == pytest.approx((result.objective - result.bound) / abs(result.objective))
    assert result.gap > 0.0
