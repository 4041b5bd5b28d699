"""The explicit MPC of the servo paper (sections II and III-C/D) as hil builds it: regions,
controllers, search tree, and how fast a law is evaluated against the online QP.

The paper's figures for FOH, H_t = H_u = 3, H_p = 50, ±1000 mA: 25 regions, 11 controllers,
a tree of 127 nodes and depth 7. What it leaves open is measured here: the parameter box the
regions are computed over (:func:`box_sweep`), and whether the tree separates controllers (as
hil's does: a leaf needs one law) or regions (:func:`region_tree`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from hil.controllers.servo.empc import ExplicitLaw, ExplicitSolver, build_explicit_law
from hil.controllers.servo.empc_tree import Polyhedron, SequentialSearch, build_tree
from hil.controllers.servo.mpc import DaqpSolver, MpcConfig, TrajectoryMpc
from hil.controllers.servo.references import Reference, Sine
from hil.controllers.servo.sim import simulate
from hil.paper.servo_conditions import ServoConditions

PAPER_EMPC = {"regions": 25, "controllers": 11, "tree_nodes": 127, "tree_depth": 7}
#: section III-C: sequential search is out of reach on the drive's DSP beyond these
PAPER_SEQUENTIAL = {"ht": 2, "regions": 15, "hyperplanes": 50}
PAPER_TREE_HT = 6  # "up to H_t = H_u = 6" with the binary search tree


def mpc_config(c: ServoConditions, ht: int) -> MpcConfig:
    """The paper's MPC at H_t = H_u = ``ht``: FOH-ERT, its H_p, Q, R and current limit."""
    return MpcConfig(ht=ht, hu=ht, hp=c.hp, ert="foh", q=c.q, r=c.r, u_min=-c.limit_ma,
                     u_max=c.limit_ma)


def region_tree(law: ExplicitLaw) -> dict[str, int]:
    """Nodes and depth of a tree that separates every region (one label per region), where
    hil's separates controllers."""
    polyhedra = [Polyhedron(r.A, r.b, r.boundary) for r in law.solution.regions]
    tree = build_tree(polyhedra, np.arange(len(polyhedra)), law.box.lower, law.box.upper,
                      covered=law.solution.covers_box)
    return {"nodes": tree.nodes, "depth": tree.depth}


def law_figures(law: ExplicitLaw, with_region_tree: bool = True) -> dict[str, Any]:
    """The figures of one explicit law: ``hil empc build``'s, the facets a sequential search
    tests at worst (every region's own, box facets left out: the box is checked first) and,
    with ``with_region_tree``, the tree over regions."""
    figures = {key: law.summary()[key] for key in
               ("regions", "controllers", "tree_nodes", "tree_depth", "hyperplanes", "build_s")}
    figures["ht"] = law.config.ht
    figures["sequential_facets"] = int(sum(np.count_nonzero(~r.boundary)
                                           for r in law.solution.regions))
    if with_region_tree:
        tree = region_tree(law)
        figures["region_tree_nodes"], figures["region_tree_depth"] = tree["nodes"], tree["depth"]
    return figures


def build_laws(c: ServoConditions, echo: Callable[[str], None]) -> dict[int, ExplicitLaw]:
    """The explicit law at every H_t = H_u of ``empc_horizons`` (default box)."""
    laws = {}
    for ht in c.empc_horizons:
        law = laws[ht] = build_explicit_law(mpc_config(c, ht))
        echo(f"explicit MPC, H_t = H_u = {ht}: {len(law.solution.regions)} regions "
             f"({law.build_s:.1f} s)")
    return laws


def box_sweep(c: ServoConditions, echo: Callable[[str], None]) -> list[dict[str, Any]]:
    """The law at H_t = H_u = ``empc_ht`` over boxes ``scale`` times the default (every
    half-width but u's): how the regions and trees grow with a box the paper does not give."""
    rows = []
    for scale in c.sweep_box_scale:
        law = build_explicit_law(mpc_config(c, c.empc_ht), box=f"scale={scale:g}")
        rows.append({"scale": scale, **law_figures(law)})
        echo(f"explicit MPC, box x{scale:g}: {rows[-1]['regions']} regions")
    return rows


def describe_controllers(law: ExplicitLaw) -> list[str]:
    """Each controller (numbered from 1 as the paper does: 1 is the unconstrained law) by
    the smallest active set among its regions: which predicted currents sit at a limit."""
    hu = law.config.hu
    described = []
    for c in range(law.n_controllers):
        sets = [r.active for r, label in zip(law.solution.regions, law.labels, strict=True)
                if label == c]
        active = min(sets, key=len)
        parts = [f"u({j % hu}) at {'+' if j < hu else '-'}max" for j in active]
        described.append(", ".join(parts) or "unconstrained")
    return described


def closed_loop_thetas(law: ExplicitLaw, c: ServoConditions, count: int) -> np.ndarray:
    """Parameter vectors θ the online MPC meets in closed loop on the published model: the
    10 Hz sine at the current limit (saturated: constraints active) and the position
    disturbance, ``count`` of each at most."""
    from hil.controllers.servo.references import position_disturbance

    seen: list[np.ndarray] = []

    class Recording(TrajectoryMpc):
        def step(self, position_deg: float, t_s: float) -> float:
            u = super().step(position_deg, t_s)
            seen.append(self._theta.copy())
            return u

    push = position_disturbance(0.0, c.torque_ma, c.push_start_s, c.push_end_s)
    scenarios: Sequence[tuple[Reference, Any, float]] = (
        (Sine(c.amplitude_deg, max(c.frequencies_hz)), None, count * 5e-4),
        (push.reference, push.disturbance, max(count * 5e-4, c.push_end_s + 0.05)))
    for reference, disturbance, seconds in scenarios:
        start = len(seen)
        simulate(Recording(reference, law.config), reference, seconds,
                 current_limit_ma=law.config.u_max, disturbance=disturbance)
        del seen[start + count:]
    return np.array(seen)


def evaluation_times(law: ExplicitLaw, thetas: np.ndarray, repeat: int = 3
                     ) -> dict[str, dict[str, float]]:
    """Δu(0|k) from θ per call [us] (p50, p99): the tree descent (the controller's hot path),
    a sequential search over the regions, and the online QP (daqp, its unconstrained fast
    path first), on the same θ in this process; and the share of θ the QP path solved."""
    online = DaqpSolver(law.qp)
    explicit = ExplicitSolver(law, DaqpSolver(law.qp))
    regions = [Polyhedron(r.A, r.b, r.boundary) for r in law.solution.regions]
    sequential = SequentialSearch(regions, law.labels.tolist(), law.box.lower, law.box.upper)
    P, gains, offsets = law.P, law.gains, law.offsets

    def sequential_law(theta: np.ndarray) -> float:
        phi = P @ theta
        index = sequential(phi)
        return float(gains[index] @ phi + offsets[index])

    times = {name: _per_call_us(fn, thetas, repeat) for name, fn in
             (("tree", explicit.solve), ("sequential", sequential_law), ("online", online.solve))}
    online.counts = dict.fromkeys(online.counts, 0)
    for theta in thetas:
        online.solve(theta)
    result = {name: {"p50": float(np.percentile(us, 50)), "p99": float(np.percentile(us, 99))}
              for name, us in times.items()}
    result["online"]["qp_share"] = online.counts["qp"] / max(1, len(thetas))
    return result


def _per_call_us(fn: Callable[[np.ndarray], Any], thetas: np.ndarray,
                 repeat: int) -> np.ndarray:
    clock = time.perf_counter_ns
    out = np.empty(len(thetas) * repeat)
    k = 0
    for _ in range(repeat):
        for theta in thetas:
            start = clock()
            fn(theta)
            out[k] = clock() - start
            k += 1
    return out / 1e3
