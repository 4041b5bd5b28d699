"""MPC of the servo paper: velocity form, prediction, ERT, condensed QP, solvers, Kalman, modulo."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from hil.controllers.servo.kalman import KalmanTuning, SteadyStateKalman
from hil.controllers.servo.model import published_axis_model
from hil.controllers.servo.mpc import (
    REFERENCE_BLOCK,
    CvxpyReferenceSolver,
    DaqpSolver,
    MpcConfig,
    TrajectoryMpc,
    condense,
    prediction_matrices,
    reference_expansion,
    velocity_form,
)
from hil.controllers.servo.pid import CascadedPid, PidConfig
from hil.controllers.servo.references import Hold, Modulo360, Ramp, Sine
from hil.controllers.servo.sim import rest_state, simulate
from hil.errors import ConfigError, HilError

MODEL = published_axis_model()


def test_velocity_form_reproduces_the_plant_output():
    """Eq. (2)-(5) driven by Δu gives the same y as eq. (1) driven by u."""
    A, B, C = velocity_form(MODEL)
    rng = np.random.default_rng(0)
    u = np.cumsum(rng.normal(0, 50, 400))
    xp = rest_state(MODEL, 3.0)
    xp_prev = xp.copy()
    x = np.concatenate([xp - xp_prev, MODEL.C @ xp])
    u_prev = 0.0
    for k in range(u.size):
        xp_prev, xp = xp, MODEL.A @ xp + MODEL.B[:, 0] * u[k]
        x = A @ x + B[:, 0] * (u[k] - u_prev)
        u_prev = u[k]
        assert (C @ x).item() == pytest.approx((MODEL.C @ xp).item(), abs=1e-9)
    np.testing.assert_allclose(x[:4], xp - xp_prev, atol=1e-12)


@pytest.mark.parametrize(("hp", "hu"), [(50, 8), (50, 3), (10, 10), (7, 1)])
def test_prediction_matrices_match_brute_force_simulation(hp, hu):
    A, B, C = velocity_form(MODEL)
    Psi, Theta = prediction_matrices(A, B, C, hp, hu)
    assert Psi.shape == (hp, 5) and Theta.shape == (hp, hu)
    rng = np.random.default_rng(hp * 100 + hu)
    for _ in range(5):
        x0 = rng.normal(size=5) * np.array([1e-2, 1e-2, 1e-5, 1e-5, 10.0])
        dU = rng.normal(0, 200, hu)
        x, ys = x0.copy(), []
        for i in range(hp):
            x = A @ x + B[:, 0] * (dU[i] if i < hu else 0.0)
            ys.append((C @ x).item())
        np.testing.assert_allclose(Psi @ x0 + Theta @ dU, ys, rtol=1e-10, atol=1e-12)


def test_foh_expansion_is_the_papers_lambda_and_extrapolates_a_line():
    ht, hp = 6, 10
    T = reference_expansion(ht, hp, "foh")
    np.testing.assert_array_equal(T[: ht - 2], np.eye(ht)[: ht - 2])
    lam = np.array([[ht - i for i in range(ht - 1, hp + 1)],
                    [i - ht + 1 for i in range(ht - 1, hp + 1)]], dtype=float)
    np.testing.assert_array_equal(lam[:, :3], [[1, 0, -1], [0, 1, 2]])  # as printed
    np.testing.assert_array_equal(T[ht - 2:, ht - 2:].T, lam)
    line = 0.3 + 0.05 * np.arange(1, ht + 1)
    np.testing.assert_allclose(T @ line, 0.3 + 0.05 * np.arange(1, hp + 1))


def test_zoh_expansion_holds_the_last_sample_and_ht1_is_setpoint_tracking():
    r = np.array([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(reference_expansion(3, 6, "zoh") @ r, [1, 2, 3, 3, 3, 3])
    np.testing.assert_array_equal(reference_expansion(1, 4, "zoh") @ [7.0], [7, 7, 7, 7])


@pytest.mark.parametrize("ert", ["zoh", "foh"])
def test_condensed_cost_equals_the_cost_of_eq7(ert):
    cfg = MpcConfig(ht=4, hu=5, hp=30, ert=ert, q=np.linspace(1e5, 1e6, 30), r=[1, 2, 3, 4, 5])
    qp = condense(cfg)
    A, B, C = velocity_form(MODEL)
    rng = np.random.default_rng(1)
    theta = qp.theta(rng.normal(size=5) * 1e-3, 12.0, rng.normal(size=4))
    x0, r = theta[:5], theta[6:]

    def cost7(dU):
        x, total = x0.copy(), float(np.sum(np.asarray(cfg.r) * dU**2))
        for i in range(1, cfg.hp + 1):
            x = A @ x + B[:, 0] * (dU[i - 1] if i <= cfg.hu else 0.0)
            if i <= cfg.ht - 2:
                ref = r[i - 1]
            elif ert == "zoh":
                ref = r[min(i, cfg.ht) - 1]
            else:
                ref = r[cfg.ht - 2] + (i - cfg.ht + 1) * (r[cfg.ht - 1] - r[cfg.ht - 2])
            total += cfg.q[i - 1] * ((C @ x).item() - ref) ** 2
        return total

    def cost9(dU):
        return 0.5 * dU @ qp.H @ dU + theta @ qp.F @ dU

    d1, d2 = rng.normal(0, 100, 5), rng.normal(0, 100, 5)
    assert cost9(d1) - cost9(d2) == pytest.approx(cost7(d1) - cost7(d2), rel=1e-9)


def _random_parameters(cfg: MpcConfig, count: int, seed: int, y_span: float):
    """θ from a closed-loop run (physical velocities), random last input and reference."""
    rng = np.random.default_rng(seed)
    ref = Sine(amplitude=y_span, frequency=3.0)
    run = simulate(CascadedPid(ref, PidConfig(u_max=1000)), ref, 1.0, wrap=False)
    xs, x = [], rest_state(MODEL, 0.0)
    for u in run.current:
        x_next = MODEL.A @ x + MODEL.B[:, 0] * u
        xs.append(np.concatenate([x_next - x, MODEL.C @ x_next]))
        x = x_next
    qp = condense(cfg)
    for k in rng.choice(np.arange(200, len(xs)), count, replace=False):
        y = xs[k][-1]
        window = y + rng.normal(0, 1.5) + np.cumsum(rng.normal(0, 0.05, cfg.ht))
        yield qp.theta(xs[k], rng.uniform(cfg.u_min, cfg.u_max), window)


def _active(qp, dU, theta, rows):
    slack = (qp.W + qp.X @ theta - qp.G @ dU)[rows]
    return bool(np.any(np.abs(slack) < 1e-6))


@pytest.mark.parametrize("cfg", [
    MpcConfig(ht=4, hu=6, hp=50, ert="foh"),
    MpcConfig(ht=3, hu=3, hp=50, ert="zoh", du_min=-300.0, du_max=200.0, y_min=-0.5, y_max=0.55),
], ids=["u-bounds", "u-du-y-bounds"])
def test_online_solution_matches_cvxpy_reference(cfg):
    qp = condense(cfg)
    fast, reference = DaqpSolver(qp), CvxpyReferenceSolver(cfg)
    hu = cfg.hu
    rows = {"u": slice(0, 2 * hu), "du": slice(2 * hu, 4 * hu), "y": slice(4 * hu, None)}
    active = {"u": 0, "du": 0, "y": 0}
    paths = {"unconstrained": 0, "qp": 0, "fallback": 0}
    for theta in _random_parameters(cfg, 40, seed=hu, y_span=0.6):
        dU = fast.solve(theta)
        paths[fast.last_path] += 1
        if fast.last_path == "fallback":  # infeasible output constraints: cvxpy agrees
            with pytest.raises(HilError, match="infeasible"):
                reference.solve(theta)
            continue
        np.testing.assert_allclose(dU, reference.solve(theta), atol=1e-3)
        assert np.all(qp.G @ dU <= qp.W + qp.X @ theta + 1e-6)
        for name, sl in rows.items():
            active[name] += _active(qp, dU, theta, sl)
    assert paths["unconstrained"] >= 3 and paths["qp"] >= 10, paths
    assert active["u"] >= 5, active
    if cfg.du_max is not None:
        assert active["du"] >= 3 and active["y"] >= 3, active


def test_infeasible_output_constraints_fall_back_to_input_constraints():
    cfg = MpcConfig(ht=3, hu=3, hp=20, ert="zoh", du_min=-300.0, du_max=200.0,
                    y_min=-1.0, y_max=1.5)
    qp = condense(cfg)
    solver = DaqpSolver(qp)
    theta = qp.theta([0, 0, 0, 0, -13.5], -900.0, [-13.4, -13.4, -13.4])  # y far below y_min
    dU = solver.solve(theta)
    assert solver.last_path == "fallback"
    n_in = qp.G.shape[0] - qp.output_rows
    assert np.all(qp.G[:n_in] @ dU <= (qp.W + qp.X @ theta)[:n_in] + 1e-6)
    assert np.all(dU <= 200.0 + 1e-6) and dU[0] > 0  # pushes up, within Δu limits


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"ert": "foh", "ht": 1, "hu": 1}, "H_t >= 2"),
    ({"ht": 60}, "must not exceed"),
    ({"ert": "spline"}, "ert"),
    ({"q": [1.0, 2.0]}, "q"),
    ({"r": 0.0}, "r"),
    ({"u_min": 10.0}, "u_min"),
    ({"du_max": -1.0}, "du_min < 0 < du_max"),
])
def test_bad_configuration_is_one_clear_error(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        MpcConfig(**kwargs)


def test_steady_state_gain_from_filterpy_solves_the_riccati_equation():
    A, B, C = velocity_form(MODEL)
    tuning = KalmanTuning()
    kf = SteadyStateKalman(A, B, C, tuning)
    Qn = tuning.disturbance_step_ma**2 * B @ B.T + tuning.state_noise**2 * np.eye(5)
    P = sla.solve_discrete_are(A.T, C.T, Qn, np.array([[tuning.measurement_deg**2]]))
    gain = (P @ C.T / (C @ P @ C.T + tuning.measurement_deg**2)).ravel()
    np.testing.assert_allclose(kf.gain, gain, rtol=1e-6)
    assert np.max(np.abs(kf.observer_poles())) < 0.99


def test_kalman_recovers_the_unmeasured_states_from_position():
    A, B, C = velocity_form(MODEL)
    kf = SteadyStateKalman(A, B, C)
    rng = np.random.default_rng(3)
    x = np.array([0.0, 0.0, 0.0, 0.0, 5.0])
    kf.reset(np.array([0.01, -0.01, 0.0, 0.0, 4.0]))  # a wrong start
    first_error = None
    for _ in range(600):
        estimate = kf.update((C @ x).item())
        error = np.abs(estimate - x).max()
        first_error = first_error if first_error is not None else error
        du = rng.normal(0, 30)
        kf.predict(du)
        x = A @ x + B[:, 0] * du
    assert first_error > 1e-3
    assert error < 1e-9


def test_integral_action_removes_a_constant_disturbance_torque():
    ref = Hold(10.0)
    mpc = TrajectoryMpc(ref, MpcConfig(ht=3, hu=3))
    run = simulate(mpc, ref, 0.5, disturbance=lambda t: 300.0 if t >= 0.05 else 0.0)
    late = run.window(0.3)
    assert np.abs(run.error[run.window(0.05, 0.1)]).max() > 1e-3  # the push did move the axis
    assert np.abs(run.error[late]).max() < 1e-6
    np.testing.assert_allclose(run.current[late], -300.0, atol=1e-3)


def test_command_never_leaves_the_current_limit():
    ref = Sine(2.0, 10.0)
    mpc = TrajectoryMpc(ref, MpcConfig(u_min=-1000.0, u_max=1000.0))
    run = simulate(mpc, ref, 0.3, current_limit_ma=1e9)  # the plant would accept more
    assert np.abs(run.current).max() <= 1000.0 + 1e-6
    assert mpc.solver.counts["qp"] > 0  # the constraints were active


@pytest.mark.parametrize("ert", ["zoh", "foh"])
def test_reference_crossing_360_gives_the_same_commands_as_a_continuous_one(ert):
    ramp = Ramp(speed_deg_s=36.0, offset=359.0)  # the reference crosses 360 at t = 28 ms
    cfg = MpcConfig(ht=4, hu=4, ert=ert)
    wrapped = simulate(TrajectoryMpc(Modulo360(ramp), cfg), Modulo360(ramp), 0.1, wrap=True)
    continuous = simulate(TrajectoryMpc(ramp, cfg), ramp, 0.1, wrap=False)
    assert wrapped.position.max() > 361.0 and wrapped.reference.min() < 1.0  # both wrapped
    np.testing.assert_allclose(wrapped.current, continuous.current, atol=1e-6)
    after_start = wrapped.window(0.02)  # the start from rest saturates; the crossing must not
    assert np.abs(np.diff(wrapped.current[after_start])).max() < 100.0


def test_reference_near_zero_and_axis_near_360_take_the_short_way():
    mpc = TrajectoryMpc(Hold(0.5), MpcConfig(ht=3, hu=3))
    run = simulate(mpc, Hold(0.5), 0.3, start_deg=359.5)
    assert abs(run.position[-1] - 360.5) < 1e-4  # moved +1 deg, not -359
    assert np.all(run.position > 359.0)


def test_prediction_starts_with_the_applied_command():
    ref = Sine(2.0, 10.0)
    mpc = TrajectoryMpc(ref, MpcConfig(ht=4, hu=4, hp=50))
    mpc.reset()
    u = 0.0
    for k in range(20):
        u = mpc.step(float(ref.position(np.array([k * MODEL.dt]))[0]), k * MODEL.dt)
    u_pred, y_pred = mpc.prediction()
    assert u_pred.shape == (50,) and y_pred.shape == (50,)
    assert u_pred[0] == pytest.approx(u)
    assert np.all(u_pred[4:] == u_pred[3])  # Δu = 0 beyond H_u
    # the definitions: û = u(k-1) + the moves so far, ŷ = Ψ x̂(k|k) + Θ ΔU
    n_x, theta, moves = mpc.qp.n_x, mpc._theta, mpc._dU
    np.testing.assert_allclose(u_pred[:4], theta[n_x] + np.cumsum(moves), rtol=0, atol=1e-9)
    np.testing.assert_allclose(y_pred, mpc.qp.Psi @ theta[:n_x] + mpc.qp.Theta @ moves,
                               rtol=1e-12, atol=1e-9)


def test_reference_samples_from_the_block_equal_direct_evaluation():
    """On the sample grid the window comes from a block evaluated at once (across a block
    boundary too), with whether it wraps 360 -> 0 worked out for the block; off the grid both
    are evaluated directly: the same values and the same answer either way."""
    for reference in (Sine(amplitude=2.0, frequency=10.0), Modulo360(Ramp(speed_deg_s=9000.0))):
        mpc = TrajectoryMpc(reference, MpcConfig(ht=8, hu=8))
        dt = mpc.dt
        wrapped = 0
        for k in (0, 5, REFERENCE_BLOCK - 3, REFERENCE_BLOCK, 3 * REFERENCE_BLOCK + 17,
                  *range(70, 90)):
            t = k * dt
            direct = reference.position(t + dt * np.arange(1, 9))
            raw, wraps = mpc._reference_ahead(t)
            # equal, or a whole turn apart right at the wrap of the modulo reference
            np.testing.assert_allclose((raw - direct + 180.0) % 360.0 - 180.0, 0.0, atol=1e-9)
            assert wraps == (np.abs(np.diff(raw)).max() >= 180.0)
            wrapped += wraps
        assert (wrapped > 0) == isinstance(reference, Modulo360)
        off_grid = 0.3 * dt + 7 * dt
        raw, wraps = mpc._reference_ahead(off_grid)
        np.testing.assert_allclose(raw, reference.position(off_grid + dt * np.arange(1, 9)),
                                   atol=0)
        assert not wraps
