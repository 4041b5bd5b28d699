"""Binary search tree: descent = sequential search, logarithmic depth, holes and the box."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.controllers.servo.empc_tree import (
    NOT_FOUND,
    OUTSIDE_BOX,
    Polyhedron,
    SequentialSearch,
    build_tree,
)
from hil.controllers.servo.mpc import MpcConfig
from hil.controllers.servo.mpqp import solve_mpqp
from tests.controllers.servo.test_mpqp import box_samples, double_integrator, region_samples

pytestmark = [pytest.mark.slow]  # builds explicit MPC trees: seconds each


def polyhedra(solution):
    return [Polyhedron(r.A, r.b, r.boundary) for r in solution.regions]


@pytest.fixture(scope="module")
def law(explicit_law):
    return explicit_law(MpcConfig(ht=3, hu=3, hp=50, ert="foh"))


@pytest.fixture(scope="module")
def many_regions():
    """Double integrator, horizon 6, |x0| <= 20: some 70 regions, each its own law."""
    problem = double_integrator(horizon=6, box=20.0)
    solution = solve_mpqp(problem)
    labels = np.arange(len(solution.regions))
    assert solution.covers_box
    tree = build_tree(polyhedra(solution), labels, problem.lower, problem.upper, covered=True)
    return solution, labels, tree


def sample_points(lower, upper, solution, rng, count):
    """Uniform in the box, inside every region, and around the box (outside points)."""
    inside, _ = region_samples(solution, rng, 10)
    centre, half = 0.5 * (upper + lower), 0.5 * (upper - lower)
    around = centre + half * rng.uniform(-1.3, 1.3, (count // 4, lower.size))
    return np.vstack([box_samples(lower, upper, rng, count), inside, around])


def reference_depth(tree, node=0):
    if tree.plane[node] < 0:
        return 0
    return 1 + max(reference_depth(tree, tree.left[node]), reference_depth(tree, tree.right[node]))


@pytest.mark.parametrize("case", ["servo", "many_regions"])
def test_tree_descent_equals_sequential_search(case, law, many_regions):
    if case == "servo":
        solution, labels, tree = law.solution, law.labels, law.tree
    else:
        solution, labels, tree = many_regions
    lower, upper = solution.problem.lower, solution.problem.upper
    sequential = SequentialSearch(polyhedra(solution), labels, lower, upper)
    descend = tree.evaluator()
    rng = np.random.default_rng(4)
    points = sample_points(lower, upper, solution, rng, 20000)
    results = np.array([descend(p) for p in points])
    expected = np.array([sequential(p) for p in points])
    assert np.array_equal(results, expected)
    assert np.count_nonzero(results == OUTSIDE_BOX) > 1000
    assert set(results[results >= 0]) == set(labels)  # every law reached
    assert NOT_FOUND not in results  # the regions cover the box


def test_tree_shape(law, many_regions):
    for tree in (law.tree, many_regions[2]):
        assert tree.nodes == 2 * tree.leaves - 1  # a full binary tree
        assert tree.depth == reference_depth(tree)
        internal = tree.plane >= 0
        assert np.all(tree.left[internal] > np.flatnonzero(internal))
        assert np.all(tree.label[~internal] >= 0)


def test_depth_is_logarithmic_in_the_region_count(many_regions):
    """At most twice a perfectly balanced tree's depth, far below a sequential search."""
    solution, _, tree = many_regions
    regions = len(solution.regions)
    assert regions >= 60
    assert tree.depth <= 2 * math.ceil(math.log2(regions))
    assert tree.depth < regions / 5


def test_paper_problem_tree(law):
    """Paper: 25 regions, 11 controllers, 127 nodes, depth 7 (see the report for ours)."""
    tree = law.tree
    assert tree.depth <= 2 * math.ceil(math.log2(law.n_controllers))
    assert tree.planes_used < sum(r.A.shape[0] for r in law.solution.regions)


def test_a_hole_in_the_partition_is_reported_not_filled(law):
    """Drop one region: its points give NOT_FOUND in the tree and the sequential search."""
    solution = law.solution
    missing = 5
    kept = [i for i in range(len(solution.regions)) if i != missing]
    regions = [polyhedra(solution)[i] for i in kept]
    labels = np.arange(len(kept))
    lower, upper = solution.problem.lower, solution.problem.upper
    tree = build_tree(regions, labels, lower, upper).evaluator()
    sequential = SequentialSearch(regions, labels, lower, upper)
    rng = np.random.default_rng(5)
    inside, owners = region_samples(solution, rng, 50)
    for p in inside[owners == missing]:
        assert tree(p) == sequential(p) == NOT_FOUND
    for p in inside[owners != missing][:300]:
        assert tree(p) == sequential(p) >= 0


def test_parameters_without_a_feasible_qp_are_not_found():
    """State constraints: part of the box has no feasible QP, so no region. The tree (not
    told the regions cover the box) answers NOT_FOUND exactly where the sequential search
    does."""
    problem = double_integrator(horizon=4, box=8.0, x_max=10.0)
    solution = solve_mpqp(problem)
    assert not solution.covers_box
    labels = solution.law_labels(slice(0, 1))
    tree = build_tree(polyhedra(solution), labels, problem.lower, problem.upper).evaluator()
    sequential = SequentialSearch(polyhedra(solution), labels, problem.lower, problem.upper)
    rng = np.random.default_rng(6)
    points = sample_points(problem.lower, problem.upper, solution, rng, 5000)
    results = np.array([tree(p) for p in points])
    assert np.array_equal(results, [sequential(p) for p in points])
    assert np.count_nonzero(results == NOT_FOUND) > 500


def test_outside_box_and_nan_are_never_evaluated(law):
    descend = law.tree.evaluator()
    lower, upper = law.box.lower, law.box.upper
    centre = 0.5 * (lower + upper)
    assert descend(centre) >= 0
    for k in range(lower.size):
        for value in (upper[k] + 1e-6 * (upper[k] - lower[k]), lower[k] - 1e-3, np.nan):
            p = centre.copy()
            p[k] = value
            assert descend(p) == OUTSIDE_BOX
    edge = upper.copy()
    assert descend(edge) >= 0  # the box boundary itself is inside
