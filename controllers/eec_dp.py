"""Exact solver of the EEC's horizon problem: dynamic programming over relay schedules.

The MILP of :class:`controllers.eec.EECMilp` couples the peripherals only through the peak:
each peripheral's dwell and level bounds are its own, its energy (J1) is additive over steps,
and the peak (J2) is the highest of the step peaks ``table[i, combination of local states]``.
So, for a peak cap ``Z``, the least energy ``f(Z)`` is a shortest path through the product of
the peripherals' state graphs (state of one peripheral after step i: relay on/off, steps of
dwell still to keep, on-steps so far - the level bounds are bounds on that counter), with the
step-combinations above ``Z`` removed. The optimum is ``min_Z w1 f(Z) + peak_cost(Z)`` over the
candidate levels, and ``f`` only falls as ``Z`` rises, so a few caps settle it:

* a DP at cap ``Z`` returns a plan of peak ``p <= Z``: every cap in ``[p, Z]`` has the same
  ``f``, so that interval is settled by ``w1 f(Z) + peak_cost(p)``;
* every lower cap has ``f >= f(Z)``, and ``f`` is at least the sum of the peripherals' own
  least energies when each alone must stay under the cap (single-peripheral DPs, all caps at
  once): a cap whose bound cannot beat the best plan is never solved.

Why not the MILP: its LP relaxation spreads fractional runs over the horizon, so HiGHS proves
optimality by root cuts and branching (0.3-0.7 s on the hard instants of a run). Here each DP
step is a handful of numpy operations on ~150 x 150 joint states, and the bound usually stops
the search after one to three caps. The result is exactly the MILP's optimum (same step peaks,
same costs): ``tests/controllers/test_eec_dp.py`` checks it on recorded decision instants.
Written for two peripherals' joint state (any number would multiply the state space).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

OFF, ON, START = 0, 1, 2


@dataclass
class Layer:
    """One peripheral's states after a step and the edges into them, per local state class:
    ``edges[k]`` is a list of (dst, src) index pairs with unique dst (min-plus layers)."""

    states: np.ndarray                                # static state ids, active after the step
    edges: list[list[tuple[np.ndarray, np.ndarray]]]  # [class][layer] -> (dst, src)


@dataclass
class DPResult:
    u: np.ndarray | None    # devices x H (0/1) or None when infeasible
    energy_cost: float      # w1 * J1 part of the objective
    peak: float             # the plan's peak (step-peak table, at least z0)
    caps: int               # joint DPs solved

    def objective(self, peak_cost: Callable[[float], float], incumbent: float) -> float:
        """This plan's objective, or the incumbent's when the search found nothing better."""
        return incumbent if self.u is None else self.energy_cost + peak_cost(self.peak)


class DeviceGraph:
    """One peripheral's static state space: id = (u * R + r) * (H + 1) + c."""

    def __init__(self, H: int, dwell: int, max_fixed: int) -> None:
        self.H, self.L = H, dwell
        self.R = max(dwell, max_fixed, 1) + 1
        R, C = self.R, H + 1
        self.n = 2 * R * C
        u, r, c = np.unravel_index(np.arange(self.n), (2, R, C))
        self.u, self.r, self.c = u, r, c
        after = max(dwell - 1, 0)

        def sid(uu: np.ndarray, rr: np.ndarray, cc: np.ndarray) -> np.ndarray:
            return (uu * R + rr) * C + cc

        keep = np.maximum(r - 1, 0)
        off_keep = u == 0
        stop = (u == 1) & (r == 0)
        on_keep = (u == 1) & (c < H)
        start = (u == 0) & (r == 0) & (c < H)
        ids = np.arange(self.n)
        # (src, dst) of each class of the step's local state
        moves = [
            (np.concatenate([ids[off_keep], ids[stop]]),
             np.concatenate([sid(0 * u[off_keep], keep[off_keep], c[off_keep]),
                             sid(0 * u[stop], after + 0 * r[stop], c[stop])])),
            (ids[on_keep], sid(u[on_keep], keep[on_keep], c[on_keep] + 1)),
            (ids[start], sid(1 + 0 * u[start], after + 0 * r[start], c[start] + 1)),
        ]
        # each class's moves split into groups with distinct destinations (min-plus layers)
        self.moves: list[list[tuple[np.ndarray, np.ndarray]]] = []
        for src, dst in moves:
            rank = np.zeros(dst.size, dtype=int)
            seen: dict[int, int] = {}
            for e, d in enumerate(dst.tolist()):
                rank[e] = seen.get(d, 0)
                seen[d] = rank[e] + 1
            self.moves.append([(src[rank == k], dst[rank == k]) for k in range(rank.max() + 1)])

    def initial(self, u_prev: float, fixed: int) -> int:
        return int((int(u_prev) * self.R + min(int(fixed), self.R - 1)) * (self.H + 1))

    def layers(self, start_id: int, c_lo: np.ndarray, c_hi: np.ndarray) -> list[Layer]:
        """The reachable states after each step within the level bounds, and their edges."""
        active = np.array([start_id])
        out = []
        pos = np.full(self.n, -1)
        fresh = np.zeros(self.n, dtype=bool)
        for i in range(self.H):
            pos[:] = -1
            pos[active] = np.arange(active.size)
            inside = (self.c >= c_lo[i]) & (self.c <= c_hi[i])
            kept = [[(pos[s][ok], d[ok]) for s, d in groups
                     for ok in [(pos[s] >= 0) & inside[d]]] for groups in self.moves]
            fresh[:] = False
            for groups in kept:
                for _, d in groups:
                    fresh[d] = True
            new = np.flatnonzero(fresh)
            pos[:] = -1
            pos[new] = np.arange(new.size)
            out.append(Layer(new, [[(pos[d], s) for s, d in groups if d.size]
                                   for groups in kept]))
            active = new
        return out

def relax(V: np.ndarray, edges: list[tuple[np.ndarray, np.ndarray]], size: int, axis: int
          ) -> np.ndarray:
    """Min-plus image of V along ``axis`` through one class's edges (inf where none)."""
    shape = list(V.shape)
    shape[axis] = size
    X = np.full(shape, np.inf)
    for dst, src in edges:
        if axis == 0:
            X[dst] = np.minimum(X[dst], V[src])
        else:
            X[:, dst] = np.minimum(X[:, dst], V[:, src])
    return X


class ScheduleDP:
    """The exact optimum of one horizon for two peripherals (see the module docstring).

    ``costs[j]``: (H, 3) cost of peripheral j's local state class (off, on, starting) in
    each step; ``table``: (H, 9) step peaks of the MILP; ``peak_cost``: the J2 part of the
    objective as a function of the peak.
    """

    def __init__(self, graphs: list[DeviceGraph]) -> None:
        if len(graphs) != 2:
            raise ValueError(f"the schedule DP is written for 2 peripherals, got {len(graphs)}")
        self.graphs = graphs

    def solve(self, layers: list[list[Layer]], costs: list[np.ndarray], table: np.ndarray,
              z0: float, levels: np.ndarray, peak_cost: Callable[[float], float],
              best: float = math.inf, deadline: float = math.inf) -> tuple[DPResult, float]:
        """(best plan found, lower bound of the objective): caps best-first by their lower
        bound until none can beat the best plan (the bound is then the optimum) or the
        ``deadline`` (``time.perf_counter``) passes. A plan is returned only if it beats
        ``best``, the incumbent's objective (else ``u`` is None)."""
        caps = np.concatenate([[z0], levels])
        pc = np.array([peak_cost(z) for z in caps])
        sep = self.separate_bound(layers, costs, table, caps)
        known = np.zeros(caps.size)
        open_ = np.isfinite(sep)
        result = DPResult(None, math.nan, math.nan, 0)
        while open_.any():
            lb = np.where(open_, np.maximum(sep, known) + pc, np.inf)
            k = int(np.argmin(lb))
            if lb[k] >= best - 1e-12 * abs(best):
                return result, best
            if time.perf_counter() > deadline:
                return result, float(lb[k])
            result.caps += 1
            found = self.joint(layers, costs, table <= caps[k] + 1e-9)
            if found is None:
                open_[: k + 1] = False
                continue
            u, energy, classes = found
            peak = max(z0, float(table[np.arange(table.shape[0]), classes].max()))
            kp = int(np.searchsorted(caps, peak - 1e-9))
            open_[kp: k + 1] = False
            known[:kp] = np.maximum(known[:kp], energy)
            if energy + peak_cost(peak) < best:
                best = energy + peak_cost(peak)
                result = DPResult(u, energy, peak, result.caps)
        return result, best

    def separate_bound(self, layers: list[list[Layer]], costs: list[np.ndarray],
                       table: np.ndarray, caps: np.ndarray) -> np.ndarray:
        """Per cap, the sum of each peripheral's least energy when it alone (the other one
        off) must keep every step peak under the cap: a lower bound of the joint least
        energy (inf: no plan)."""
        total = np.zeros(caps.size)
        for j, dev_layers in enumerate(layers):
            alone = table[:, [3 * k if j == 0 else k for k in range(3)]]  # (H, 3)
            V = np.zeros((caps.size, 1))
            for i, layer in enumerate(dev_layers):
                size = layer.states.size
                new = np.full((caps.size, size), np.inf)
                for k in range(3):
                    cost = np.where(alone[i, k] <= caps + 1e-9, costs[j][i, k], np.inf)
                    new = np.minimum(new, relax(V, layer.edges[k], size, 1) + cost[:, None])
                V = new
            total += V.min(axis=1)
        return total

    def joint(self, layers: list[list[Layer]], costs: list[np.ndarray], allowed: np.ndarray
              ) -> tuple[np.ndarray, float, np.ndarray] | None:
        """Least-energy plan with every step's combination in ``allowed`` (H, 9): (u,
        energy cost, combination index per step), or None if there is none."""
        H = allowed.shape[0]
        la, lb = layers
        V = np.zeros((1, 1))
        history = []
        for i in range(H):
            m1, m2 = la[i].states.size, lb[i].states.size
            X = [relax(V, la[i].edges[a], m1, 0) + costs[0][i, a] for a in range(3)]
            new = np.full((m1, m2), np.inf)
            for b in range(3):
                ok = [a for a in range(3) if allowed[i, 3 * a + b]]
                if not ok:
                    continue
                M = X[ok[0]] if len(ok) == 1 else np.minimum.reduce([X[a] for a in ok])
                new = np.minimum(new, relax(M, lb[i].edges[b], m2, 1) + costs[1][i, b])
            history.append(V)
            V = new
        if not np.isfinite(V).any():
            return None
        s1, s2 = (int(x) for x in np.unravel_index(int(np.argmin(V)), V.shape))
        energy = float(V[s1, s2])
        value = energy
        u = np.zeros((2, H), dtype=int)
        classes = np.zeros(H, dtype=int)
        for i in range(H - 1, -1, -1):
            prev = history[i]
            found = False
            for a, p1 in self._preds(la[i], s1):
                for b, p2 in self._preds(lb[i], s2):
                    if not allowed[i, 3 * a + b]:
                        continue
                    v = prev[p1, p2] + costs[0][i, a] + costs[1][i, b]
                    if abs(v - value) <= 1e-9 * max(1.0, abs(value)):
                        s1, s2, value, found = p1, p2, float(prev[p1, p2]), True
                        u[0, i], u[1, i], classes[i] = a > OFF, b > OFF, 3 * a + b
                        break
                if found:
                    break
            if not found:
                raise RuntimeError(f"schedule DP: no predecessor at step {i}")
        return u, energy, classes

    @staticmethod
    def _preds(layer: Layer, s: int) -> list[tuple[int, int]]:
        return [(k, int(src[dst == s][0])) for k in range(3) for dst, src in layer.edges[k]
                if np.any(dst == s)]
