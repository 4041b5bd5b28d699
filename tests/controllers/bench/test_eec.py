"""EEC: the fast MILP against brute force and against the cvxpy reference; fallback; horizon
modes; terminal condition.

Exactness tests use small synthetic load models whose transients end within one decision step
(then the pattern-level formulation of J2 is exact) on a coarse model grid (0.1 s).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from hil.bench.config import load_bench_config
from hil.controllers.base import BenchController, BenchEstimator, BenchObservation
from hil.controllers.bench.eec import EEC
from hil.controllers.bench.eec_costs import HorizonCosts
from hil.controllers.bench.eec_repair import feasible, repair
from hil.controllers.bench.eec_settings import EECSettings
from hil.controllers.bench.eec_solver import HorizonSolver
from hil.controllers.bench.models import DeviceModel, LinearModel, MachiningModel
from hil.controllers.bench.prediction import BenchEstimate, BenchModels, HorizonPrediction
from hil.controllers.bench.problem import BenchProblem

DT = 0.1  # model grid of the synthetic models: 10 samples per decision step


def synthetic_models(problem: BenchProblem) -> BenchModels:
    lam = 0.2
    machining = LinearModel(
        A=np.diag([lam, lam]), B=np.diag([230.0 * (1 - lam), 140.0 * (1 - lam)]),
        C=np.array([1.0, 1.0]), D=np.zeros(2), dt=DT, inputs=("M1", "M2"), rest_output=40.0,
        name="machining")

    def motor(name: str, steady: float, inrush: float) -> DeviceModel:
        # state: [relay delayed by one sample, inrush transient]; y = V u(k-1) + x_e
        return DeviceModel(LinearModel(
            A=np.array([[0.0, 0.0], [0.0, 0.1]]), B=np.array([[1.0, 0.0], [0.0, inrush]]),
            C=np.array([steady, 1.0]), D=np.zeros(2), dt=DT,
            inputs=(name, f"{name}:start"), rest_output=0.0, name=name))

    devices = {"P1": motor("P1", 110.0, 150.0), "P2": motor("P2", 80.0, 110.0)}
    return BenchModels(MachiningModel.from_linear(machining, problem.sequence), devices)


def problem_with_dwell(dwell_s: float) -> BenchProblem:
    return load_bench_config().with_dwell(dwell_s).problem


def q_trajectory(problem: BenchProblem, q0: np.ndarray, t_s: float, u: np.ndarray
                 ) -> np.ndarray:
    """Levels after each step, from eq. (10) directly (not from the MILP's bounds)."""
    out = np.empty((len(problem.resources), u.shape[1]))
    for j, res in enumerate(problem.resources):
        q = q0[j]
        for i in range(u.shape[1]):
            on = problem.sequence.on_fraction(res.consumer, t_s + i, t_s + i + 1)
            q += res.alpha * on + res.eta * u[j, i]
            out[j, i] = q
    return out


def brute_force(problem: BenchProblem, horizon: HorizonCosts, prediction: HorizonPrediction,
                est: BenchEstimate, u_prev: np.ndarray, since_switch: np.ndarray,
                q0: np.ndarray, t_s: float) -> tuple[float, np.ndarray | None]:
    """The best objective over every relay sequence, each simulated sample by sample."""
    H, nd = prediction.steps, len(problem.peripherals)
    settings = horizon.settings
    free = prediction.free(est)
    best, best_u = np.inf, None
    for bits in itertools.product((0, 1), repeat=nd * H):
        u = np.array(bits, float).reshape(nd, H)
        ok = True
        for j in range(nd):
            L = horizon.dwell_steps[j]
            seq = np.concatenate([[u_prev[j]], u[j]])
            change_steps = np.nonzero(np.diff(seq))[0]  # step index of each switch
            last = -since_switch[j]
            for step in change_steps:
                if step - last < L:
                    ok = False
                last = step
        if not ok:
            continue
        q = q_trajectory(problem, q0, t_s, u)
        for j, res in enumerate(problem.resources):
            if np.any(q[j] < res.q_min - 1e-9) or np.any(q[j] > res.q_max + 1e-9):
                ok = False
            if settings.terminal == "hold" and q[j, -1] < min(res.q0, res.q_max - res.eta) - 1e-9:
                ok = False
        if not ok:
            continue
        s_va = prediction.simulate(est, u, u_prev)
        starts = np.clip(np.diff(np.concatenate([u_prev[:, None], u], axis=1)), 0, None)
        area = float(np.sum(s_va - free) * prediction.dt)
        for j, name in enumerate(problem.peripherals):  # a late start's dwell beyond the end
            beyond = np.clip(horizon.dwell_steps[j] - (H - np.arange(H)), 0, None)
            area += float(starts[j] @ beyond) * prediction.models.devices[name].steady_va
        peak = float(s_va.max())
        cost = horizon.w1 * area + horizon.w2 * peak
        if settings.limit_va is not None:
            cost += horizon.w_limit * max(0.0, peak - settings.limit_va)
        if cost < best - 1e-12:
            best, best_u = cost, u
    return best, best_u


CASES = [
    # (t_s, q0, u_prev, since_switch steps, terminal, limit, disturbance)
    (0.0, [55.0, 65.0], [0, 0], [9, 9], "hold", 560.0, 0.0),
    (8.0, [52.0, 70.0], [1, 0], [1, 9], "none", None, 0.0),
    (12.0, [60.0, 62.0], [0, 1], [9, 1], "hold", 430.0, 30.0),
    (19.0, [51.0, 100.0], [0, 0], [2, 9], "none", 450.0, 70.0),
    (23.0, [70.0, 61.0], [1, 1], [3, 2], "hold", None, -20.0),
]


@pytest.mark.parametrize("case", CASES)
def test_milp_equals_brute_force_on_a_tiny_horizon(case):
    t_s, q0, u_prev, since, terminal, limit, dist = case
    problem = problem_with_dwell(3.0)
    models = synthetic_models(problem)
    settings = EECSettings(hp_steps=6, terminal=terminal, limit_va=limit,
                           peak_resolution_va=0.0, time_limit_s=30.0, mip_rel_gap=1e-9)
    prediction = HorizonPrediction(models, problem, 6, 10)
    solver = HorizonSolver(prediction, problem, settings)
    horizon = solver.horizon
    est = BenchEstimate(round(t_s / DT), np.array([3.0, -2.0]),
                        {"P1": np.array([u_prev[0], 5.0]), "P2": np.zeros(2)}, dist)
    u_prev, since, q0 = np.array(u_prev, float), np.array(since), np.array(q0)
    fixed = np.maximum(0, horizon.dwell_steps[0] - since)
    result = solver.solve(prediction.free(est), u_prev, fixed, q0, t_s)
    best, best_u = brute_force(problem, horizon, prediction, est, u_prev, since, q0, t_s)
    assert best_u is not None, "the brute force found no feasible sequence: bad case"
    assert result.status == "optimal"
    # equal up to the coefficients below 1e-6 of a device's power that the model drops
    assert result.objective == pytest.approx(best, rel=1e-6)
    # the plan the MILP returns is as good as the best sequence when simulated
    again, _ = brute_force(problem, horizon, prediction, est, u_prev, since, q0, t_s)
    assert again == pytest.approx(best)
    s_va = prediction.simulate(est, result.u.astype(float), u_prev)
    assert result.peak_va == pytest.approx(s_va.max(), abs=0.01)
    # the quick plan evaluation used to pick warm starts agrees
    u = result.u.astype(float)
    quick = horizon.costs(u, 1, u[1:2], u_prev, horizon.peak_table(prediction.free(est)))[0]
    assert quick == pytest.approx(result.objective, rel=1e-9)


def test_infeasible_problem_is_reported_not_raised():
    problem = problem_with_dwell(3.0)
    models = synthetic_models(problem)
    prediction = HorizonPrediction(models, problem, 6, 10)
    solver = HorizonSolver(prediction, problem, EECSettings(hp_steps=6))
    est = BenchEstimate.at_rest(models, 40)
    result = solver.solve(prediction.free(est), np.zeros(2), np.zeros(2, int),
                          np.array([30.0, 65.0]), 4.0)
    assert result.status == "infeasible" and result.u is None


@pytest.mark.parametrize("t_s, q0, u_prev", [(3.0, [56.0, 66.0], [0, 0]),
                                             (15.0, [70.0, 90.0], [1, 0])])
def test_highs_model_equals_the_cvxpy_reference(t_s, q0, u_prev):
    # imported here: cvxpy costs ~1 s of CPU to import, which every xdist worker paid when it
    # collected this module, whether it ran this test or not
    from hil.controllers.bench.eec_cvxpy import CvxpyEEC, solve_naive

    problem = problem_with_dwell(5.0)
    models = synthetic_models(problem)
    settings = EECSettings(hp_steps=10, limit_va=500.0, peak_resolution_va=0.0,
                           time_limit_s=30.0, mip_rel_gap=1e-9)
    prediction = HorizonPrediction(models, problem, 10, 10)
    solver = HorizonSolver(prediction, problem, settings)
    est = BenchEstimate.at_rest(models, round(t_s / DT))
    args = (prediction.free(est), np.array(u_prev, float), np.zeros(2, int), np.array(q0), t_s)
    fast = solver.solve(*args)
    reference = CvxpyEEC(solver.horizon).solve(*args)
    naive = solve_naive(solver.horizon, *args)
    assert fast.status == "optimal" and reference.u is not None and naive.u is not None
    assert fast.objective == pytest.approx(reference.objective, rel=1e-6)
    assert naive.objective == pytest.approx(reference.objective, rel=1e-6)


def eec_step(eec: EEC, models: BenchModels, t: float, levels: dict[str, float]):
    est = BenchEstimate.at_rest(models, round(t / models.dt))
    return eec.step(BenchObservation(t, levels, dict(eec.dwell.state), 0.0, est))


def test_failed_solve_falls_back_to_the_hysteresis_rule():
    problem = problem_with_dwell(5.0)
    models = synthetic_models(problem)
    eec = EEC(models, problem, EECSettings(hp_steps=8))
    decision = eec_step(eec, models, 5.0, {"q1": 30.0, "q2": 120.0})  # q1 far below 50
    assert decision.fallback is not None and decision.plan is None
    assert [kind for kind, _ in decision.events] == ["eec.fallback"]
    assert decision.relays == {"P1": True, "P2": False}  # the hysteresis answer
    # the dwell of that fallback switch binds the next (feasible) solves
    for t in (6.0, 7.0, 8.0, 9.0):
        assert eec_step(eec, models, t, {"q1": 55.0, "q2": 120.0}).relays["P1"] is True


def test_whole_plan_mode_applies_the_plan_without_solving():
    problem = problem_with_dwell(5.0)
    models = synthetic_models(problem)
    eec = EEC(models, problem, EECSettings(hp_steps=10, hs_steps=10))
    first = eec_step(eec, models, 0.0, {"q1": 55.0, "q2": 65.0})
    assert first.plan is not None
    applied = [first.relays]
    for t in range(1, 10):
        decision = eec_step(eec, models, float(t), {"q1": 55.0, "q2": 65.0})
        assert decision.solve is None  # no new MILP inside H_s
        applied.append(decision.relays)
    for j, name in enumerate(problem.peripherals):
        assert [r[name] for r in applied] == [bool(x) for x in first.plan.u[j]]
    assert eec_step(eec, models, 10.0, {"q1": 55.0, "q2": 65.0}).solve is not None


def test_terminal_hold_keeps_the_levels_that_none_drains():
    problem = problem_with_dwell(5.0)
    models = synthetic_models(problem)
    ends = {}
    for terminal in ("none", "hold"):
        eec = EEC(models, problem, EECSettings(hp_steps=28, terminal=terminal, limit_va=None))
        plan = eec_step(eec, models, 0.0, {"q1": 100.0, "q2": 130.0}).plan
        ends[terminal] = plan.q[:, -1]
    q1, q2 = problem.resources
    # q2 loses 70 per cycle: without a terminal condition the plan lets it fall to its
    # minimum (60) and produces nothing; "hold" must bring it back to q2(0) = 65
    assert ends["none"][1] == pytest.approx(q2.q_min)
    assert ends["hold"][1] >= q2.q0 > ends["none"][1]
    assert ends["hold"][0] >= q1.q0


def test_shifted_plan_missing_production_at_the_end_is_repaired():
    problem = problem_with_dwell(5.0)
    models = synthetic_models(problem)
    prediction = HorizonPrediction(models, problem, 12, 10)
    solver = HorizonSolver(prediction, problem, EECSettings(hp_steps=12))
    horizon = solver.horizon
    # with nothing on, q1 falls short near the end of the horizon (as a plan shifted by a
    # step usually does): the repair runs P1 over the last steps
    q0 = np.array([68.0, 80.0])
    qlo, qhi = horizon.level_bounds(q0, 0.0)
    c_lo, c_hi = np.maximum(qlo, 0), np.minimum(qhi, np.arange(12) + 1.0)
    off = np.zeros(2)
    plan = np.zeros((2, 12))
    assert not feasible(horizon, plan, off, off, c_lo, c_hi)
    repaired = repair(horizon, plan, off, off, c_lo, c_hi)
    assert repaired is not None and feasible(horizon, repaired, off, off, c_lo, c_hi)
    on = np.nonzero(repaired[0])[0]
    assert on.size and np.array_equal(on, np.arange(12 - on.size, 12))  # one final run
    assert repaired[1].sum() == 0
    # a plan that is fine is returned as it is
    good = solver.solve(prediction.free(BenchEstimate.at_rest(models)), off, np.zeros(2, int),
                        q0, 0.0).u.astype(float)
    assert np.array_equal(repair(horizon, good, off, off, c_lo, c_hi), good)


def test_models_identified_over_the_wire_load_with_their_pulse_inputs():
    """`hil identify` names inputs after recorded fields (``/ident/relays:M1_start``)."""
    import numpy as np

    from hil.bench.config import load_bench_config
    from hil.controllers.bench.models import MachiningModel, to_linear_model

    inputs = ["/ident/relays:M1", "/ident/relays:M1_start", "/ident/relays:M2",
              "/ident/relays:M2_start"]
    lin = to_linear_model(np.eye(1) * 0.5, np.ones((1, 4)), np.ones((1, 1)), np.zeros((1, 4)),
                          0.01, inputs, np.zeros(4), np.zeros(1), name="wire")
    assert lin.inputs == ("M1", "M1:start", "M2", "M2:start")
    sequence = load_bench_config().problem.sequence
    assert MachiningModel.from_linear(lin, sequence).model is lin


def test_eec_is_a_bench_controller_with_its_estimator():
    problem = problem_with_dwell(5.0)
    models = synthetic_models(problem)
    eec = EEC(models, problem, EECSettings(hp_steps=8))
    assert isinstance(eec, BenchController) and isinstance(eec.estimator, BenchEstimator)
    est = BenchEstimate.at_rest(models)
    obs = BenchObservation(0.0, {"q1": 30.0, "q2": 120.0}, {"P1": False, "P2": False}, 0.0, est)
    assert eec.decide(obs) == {"P1": True, "P2": False}    # the fallback's answer, as a dict
    with pytest.raises(TypeError, match="BenchEstimate"):
        eec.decide(BenchObservation(1.0, {"q1": 55.0, "q2": 120.0}, {}, 0.0))
