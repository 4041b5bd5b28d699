"""mpQP: the explicit law against online QP solvers, the partition of the box, irredundancy."""

from __future__ import annotations

import daqp
import numpy as np
import pytest

from hil.controllers.servo.empc import build_explicit_law, relative_map
from hil.controllers.servo.mpc import DaqpSolver, MpcConfig
from hil.controllers.servo.mpqp import MpQP, solve_mpqp
from hil.errors import ConfigError

PAPER = MpcConfig(ht=3, hu=3, hp=50, ert="foh")  # Q = 1e6, R = 1, |u| <= 1000 mA


@pytest.fixture(scope="module")
def law(explicit_law):
    return explicit_law(PAPER)


def region_samples(solution, rng, per_region):
    """Points inside each region's Chebyshev ball (so every region, thin ones included)."""
    qp = solution.problem
    points, owners = [], []
    for i, region in enumerate(solution.regions):
        for _ in range(per_region):
            d = rng.normal(size=qp.n_params)
            d *= region.radius * rng.random() / np.linalg.norm(d)
            points.append(region.centre + qp.half_width * d)
            owners.append(i)
    return np.array(points), np.array(owners)


def box_samples(lower, upper, rng, count):
    return lower + (upper - lower) * rng.random((count, lower.size))


def double_integrator(horizon, box, x_max=None):
    """A textbook mpQP (x0 in R^2) with input and optional state constraints."""
    A = np.array([[1.0, 1.0], [0.0, 1.0]])
    B = np.array([0.5, 1.0])
    Sx = np.vstack([np.linalg.matrix_power(A, k) for k in range(1, horizon + 1)])
    Su = np.zeros((2 * horizon, horizon))
    for k in range(1, horizon + 1):
        for j in range(k):
            Su[2 * (k - 1):2 * k, j] = np.linalg.matrix_power(A, k - 1 - j) @ B
    H = 2 * (Su.T @ Su + 0.1 * np.eye(horizon))
    F = 2 * Sx.T @ Su
    G = np.vstack([np.eye(horizon), -np.eye(horizon)])
    W = np.ones(2 * horizon)
    X = np.zeros((2 * horizon, 2))
    if x_max is not None:
        G = np.vstack([G, Su, -Su])
        W = np.concatenate([W, np.full(4 * horizon, x_max)])
        X = np.vstack([X, -Sx, Sx])
    return MpQP(H=H, F=F, G=G, W=W, X=X, lower=np.full(2, -box), upper=np.full(2, box))


def test_paper_problem_has_21_regions_and_11_controllers(law):
    """FOH, H_t = H_u = 3, H_p = 50, |u| <= 1000 mA: 11 distinct first-move laws (the paper's
    11 controllers) over 21 regions; the 3 active sets {u_i = max, u_i = min} are degenerate."""
    solution = law.solution
    assert len(solution.regions) == 21
    assert law.n_controllers == 11
    assert solution.stats["degenerate"] == 3
    assert solution.regions[0].active == ()  # controller 0: unconstrained
    assert len({r.active for r in solution.regions}) == 21
    # Every region with u(0|k) saturated applies the same first move: u_max - u(k-1).
    upper = [i for i, r in enumerate(solution.regions) if 0 in r.active]
    assert len(set(law.labels[upper])) == 1
    c = law.labels[upper[0]]
    u = law.box.names.index("u")
    expected = np.zeros(law.gains.shape[1])
    expected[u] = -1.0
    np.testing.assert_allclose(law.gains[c], expected, atol=1e-9)
    assert law.offsets[c] == pytest.approx(PAPER.u_max, abs=1e-6)


def check_against_online_qp(law, rng, per_region, uniform_count):
    """ΔU (all H_u moves) of the region's affine law = daqp's optimum at the same θ, to 1e-8
    relative to the size of ΔU, in every region (active constraints included), at θ with
    arbitrary absolute positions (shift invariance). Returns the online solver's paths."""
    _, S = relative_map(law.qp, law.config.ht)
    online = DaqpSolver(law.qp)
    inside, owners = region_samples(law.solution, rng, per_region)
    uniform = box_samples(law.box.lower, law.box.upper, rng, uniform_count)
    paths = set()
    for k, phi in enumerate(np.vstack([inside, uniform])):
        theta = S @ phi
        y = rng.uniform(-720.0, 720.0)
        theta[law.qp.n_x - 1] += y
        theta[law.qp.n_x + 1:] += y
        expected = online.solve(theta)
        paths.add(online.last_path)
        tol = 1e-8 * max(1.0, np.abs(expected).max())
        got = law.moves(theta)
        assert got is not None
        np.testing.assert_allclose(got, expected, rtol=0, atol=tol)
        if k < owners.size:  # the point is inside region owners[k]: its law is the one used
            region = law.solution.regions[owners[k]]
            np.testing.assert_allclose(region.optimiser(phi), expected, rtol=0, atol=tol)
            code, du0 = law.first_move(theta)
            assert code == law.labels[owners[k]]
            assert du0 == pytest.approx(expected[0], abs=tol)
    return paths


def test_explicit_law_equals_online_qp_everywhere_in_the_box(law):
    paths = check_against_online_qp(law, np.random.default_rng(1), 60, 1500)
    assert paths == {"unconstrained", "qp"}


@pytest.mark.slow
def test_explicit_law_with_rate_limits_equals_online_qp():
    """Δu limits next to asymmetric u limits, H_u < H_t: more active-set combinations, some
    pruned as infeasible (|Δu| too small to reach a current limit in time)."""
    config = MpcConfig(ht=3, hu=2, hp=40, ert="zoh", du_min=-500.0, du_max=200.0,
                       u_min=-800.0, u_max=1000.0)
    law = build_explicit_law(config, box="e=20")
    assert law.solution.stats["infeasible"] > 0
    paths = check_against_online_qp(law, np.random.default_rng(8), 30, 300)
    assert paths == {"unconstrained", "qp"}


@pytest.mark.slow
def test_every_point_of_the_box_lies_in_exactly_one_region(law):
    rng = np.random.default_rng(2)
    inside, owners = region_samples(law.solution, rng, 20)
    points = np.vstack([box_samples(law.box.lower, law.box.upper, rng, 20000), inside])
    A = np.vstack([r.A for r in law.solution.regions])
    b = np.concatenate([r.b for r in law.solution.regions])
    starts = np.cumsum([0] + [r.A.shape[0] for r in law.solution.regions])[:-1]
    slack = A @ points.T - b[:, None]
    covered = np.logical_and.reduceat(slack <= 1e-9, starts, axis=0).sum(axis=0)
    interior = np.logical_and.reduceat(slack <= -1e-9, starts, axis=0).sum(axis=0)
    assert covered.min() >= 1  # no hole
    assert interior.max() <= 1  # no overlap beyond shared boundaries
    # The ball samples lie in their own region's interior and nowhere else.
    own = np.logical_and.reduceat(slack[:, -owners.size:] <= -1e-9, starts, axis=0)
    assert np.array_equal(own.argmax(axis=0), owners)


def test_no_redundant_half_space_is_kept(law):
    """Each kept row cuts its region: dropping it lets a'p exceed b (checked with scipy)."""
    # imported here, not when every xdist worker collects this module (and the two that
    # import its helpers): scipy.optimize is ~0.15 s of CPU to import
    from scipy.optimize import linprog

    for region in law.solution.regions:
        assert region.A.shape[0] == region.b.size == region.boundary.size
        for i in range(region.A.shape[0]):
            others = np.delete(np.arange(region.A.shape[0]), i)
            # max a_i'p over the other rows, capped at b_i + 1 so that it stays bounded.
            A_ub = np.vstack([region.A[others], region.A[i]])
            b_ub = np.append(region.b[others], region.b[i] + 1.0)
            res = linprog(-region.A[i], A_ub=A_ub, b_ub=b_ub, bounds=(None, None),
                          method="highs")
            assert res.status == 0
            assert -res.fun > region.b[i] + 1e-6
        # The rows flagged as box facets lie on the box boundary.
        for a, b in zip(region.A[region.boundary], region.b[region.boundary], strict=True):
            (k,) = np.flatnonzero(np.abs(a) > 1e-12)
            face = law.box.upper[k] if a[k] > 0 else law.box.lower[k]
            assert a[k] * face == pytest.approx(b, rel=1e-12)


@pytest.mark.slow
def test_state_constrained_problem_matches_daqp_and_excludes_infeasible_parameters():
    """A problem with state constraints: some active sets are pruned as infeasible, the
    regions cover exactly the parameters where the QP is feasible."""
    problem = double_integrator(horizon=4, box=8.0, x_max=10.0)
    solution = solve_mpqp(problem)
    assert solution.stats["infeasible"] > 0
    assert len(solution.regions) > 20
    rng = np.random.default_rng(3)
    feasible = infeasible = 0
    for p in box_samples(problem.lower, problem.upper, rng, 800):
        x, _, exitflag, _ = daqp.solve(problem.H, problem.F.T @ p, problem.G,
                                       problem.W + problem.X @ p)
        got = solution.optimiser(p)
        if exitflag >= 1:
            feasible += 1
            assert got is not None
            np.testing.assert_allclose(got, x, atol=1e-8 * max(1.0, np.abs(x).max()))
        else:
            infeasible += 1
            assert got is None
    assert feasible > 100 and infeasible > 100


def test_bad_problems_are_reported():
    good = double_integrator(3, 5.0)
    with pytest.raises(ConfigError, match="W has shape"):
        MpQP(H=good.H, F=good.F, G=good.G, W=good.W[:-1], X=good.X, lower=good.lower,
             upper=good.upper)
    with pytest.raises(ConfigError, match="finite"):
        MpQP(H=good.H, F=good.F, G=good.G, W=good.W, X=good.X, lower=good.lower,
             upper=np.array([1.0, np.inf]))
    with pytest.raises(ConfigError, match="upper > lower"):
        MpQP(H=good.H, F=good.F, G=good.G, W=good.W, X=good.X, lower=good.lower,
             upper=good.lower)
