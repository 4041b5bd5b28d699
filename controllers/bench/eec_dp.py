"""Exact solver of the EEC's horizon problem: a pruned dynamic program over relay schedules.

The MILP of :class:`hil.controllers.bench.eec_milp.EECMilp` couples the peripherals only through
the peak.
Each peripheral's dwell and level bounds are its own, its energy (J1, plus ``gamma3`` per
switch-on) adds up over the steps, and the peak (J2) is the highest of the step peaks
``table[i, combination of local states]`` (local state: off, on, starting). So a plan is a
path through the product of the peripherals' state graphs (state of one peripheral after step
i: relay on/off, steps of dwell still to keep, on-steps so far - the level bounds are bounds
on that counter), and its objective is the path's energy plus ``peak_cost`` of the highest
step peak along it. The search runs forward over that product, one step at a time, with the
peak cost so far in the state, and keeps it small:

* **bound pruning** (branch and bound in DP form): a partial plan is dropped when no
  completion can beat the incumbent. Its bound is the energy so far plus, for the peak
  bucket a completion may end in (between two of a few peak caps), each peripheral's least
  energy to the horizon end on its own under that cap, plus the bucket's least peak cost
  (the least over the buckets). The cost-to-go tables come from one backward DP over the
  disjoint union of the peripherals' graphs for all caps at once.
* **dominance**: of two partial plans in the same joint state, one with no higher peak cost
  and no higher energy makes the other useless; only the Pareto front is kept.
* **incumbent**: the best of the previous decision's plan (shifted by one step, kept as far
  as it stays feasible: the machining sequence is periodic, so it is usually optimal or
  close), each cap's own least-energy plans put together (feasible: nothing but the peak
  couples the peripherals), and, when the exact search grows past 200 partial plans in a
  step, a narrow beam search (the same search keeping the 32 partial plans of least bound
  per step), which finds the optimum or a near one in a few ms; the exact search then
  starts again from it.

What survives the last step is every plan strictly better than the incumbent; the best of
them (or the incumbent when none is left) is the optimum, proven. Each step is a few dozen
numpy operations on the surviving partial plans (tens to a few thousand).

Why this and not the MILP: its LP relaxation spreads fractional runs over the horizon, so
HiGHS proves optimality by root cuts and branching (0.1-0.7 s on the hard instants of a run,
seconds at H_p = 2T). An earlier version of this module solved the joint DP densely (~150 x
150 joint states a step) under a few peak caps, 20-60 ms a decision; the bounds and the beam
incumbent make most joint states provably useless. A compiled inner loop was not needed.
The result is exactly the MILP's optimum (same step peaks, same costs):
``tests/controllers/bench/test_eec_dp.py`` checks it on recorded decision instants. Any number of
peripherals works (2 successors per peripheral and step), but the state space multiplies.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

OFF, ON, START = 0, 1, 2


class DeviceGraph:
    """One peripheral's static state space: id = (u * R + r) * (H + 1) + c, where r is the
    number of steps its relay must still keep its state and c its on-steps so far.

    ``succ_dst``/``succ_cls`` (n, 2): the at most two successors of each state (keep the
    relay, switch it) and the local state class of the step that leads there (OFF, ON,
    START); a missing one is ``-1``."""

    def __init__(self, H: int, dwell: int, max_fixed: int) -> None:
        self.H, self.L = H, dwell
        self.R = max(dwell, max_fixed, 1) + 1
        R, C = self.R, H + 1
        self.n = 2 * R * C
        u, r, c = np.unravel_index(np.arange(self.n), (2, R, C))
        self.c = c
        after = max(dwell - 1, 0)
        keep = np.maximum(r - 1, 0)
        stay = np.where(u == 0, keep * C + c, (R + keep) * C + c + 1)
        stay_ok = (u == 0) | (c < H)
        switch = np.where(u == 0, (R + after) * C + c + 1, after * C + c)
        switch_ok = (r == 0) & ((u == 1) | (c < H))
        self.succ_dst = np.stack([np.where(stay_ok, stay, -1),
                                  np.where(switch_ok, switch, -1)], axis=1)
        self.succ_cls = np.stack([np.where(u == 0, OFF, ON), np.where(u == 0, START, OFF)],
                                 axis=1)

    def initial(self, u_prev: float, fixed: int) -> int:
        """The state before the first step: relay ``u_prev``, ``fixed`` steps of dwell left."""
        return int((int(u_prev) * self.R + min(int(fixed), self.R - 1)) * (self.H + 1))


@dataclass
class DPResult:
    u: np.ndarray | None    # devices x H (0/1): the best plan known, None if there is none
    objective: float        # its objective (energy + peak cost; inf when none)
    bound: float            # proven lower bound of the optimum (= objective when proven)
    expanded: int           # partial plans kept over all steps (the size of the search)


class ScheduleDP:
    """The exact optimum of one horizon (see the module docstring).

    The peripherals' graphs are joined into one disjoint union (state ids offset per
    peripheral, sentinel ``N``), so that the per-peripheral bounds of every peripheral and
    every peak cap come out of one backward pass. ``caps``: how many peak caps the bounds
    are computed for; ``beam``: width of the heuristic search run for a better incumbent when
    the exact search grows beyond ``give_up`` partial plans in a step.
    """

    def __init__(self, graphs: Sequence[DeviceGraph], caps: int = 4, beam: int = 32,
                 give_up: int = 200) -> None:
        self.graphs = list(graphs)
        self.caps, self.beam, self.give_up = caps, beam, give_up
        nd = len(self.graphs)
        self.H = self.graphs[0].H
        self.weights = 3 ** np.arange(nd - 1, -1, -1)
        self.offsets = np.cumsum([0] + [g.n for g in self.graphs])
        N = self.N = int(self.offsets[-1])
        self.dst = np.concatenate([np.where(g.succ_dst >= 0, g.succ_dst + off, N)
                                   for g, off in zip(self.graphs, self.offsets, strict=False)])
        self.cls = np.concatenate([g.succ_cls for g in self.graphs])
        self.device = np.repeat(np.arange(nd), [g.n for g in self.graphs])
        self.counter = np.concatenate([g.c for g in self.graphs])
        self.strides = (N + 1) ** np.arange(nd - 1, -1, -1)              # of a joint state key

    def cost_to_go(self, costs: np.ndarray, c_lo: np.ndarray, c_hi: np.ndarray) -> np.ndarray:
        """(M, H + 1, N + 1): for each of M class-cost tables ``costs`` (M, nd, H, 3), inf
        where a class is not allowed, the least cost from each state before step i to the
        horizon end, each peripheral alone (inf where its level bounds ``c_lo``, ``c_hi``
        (nd, H) cannot be kept; row i is inf for states that break the bounds of step
        i - 1; column N is the sentinel)."""
        H, N, M = self.H, self.N, costs.shape[0]
        h = np.full((M, H + 1, N + 1), np.inf)
        h[:, H, :N] = 0.0
        outside = np.zeros((H, N + 1))
        outside[:, :N][(self.counter < c_lo[self.device].T)
                       | (self.counter > c_hi[self.device].T)] = np.inf
        # the cost of each state's two edges in every step: (M, H, N) each
        flat = costs.reshape(M, -1, H, 3).transpose(0, 2, 1, 3).reshape(M, H, -1)
        index = self.device[:, None] * 3 + self.cls                     # (N, 2)
        keep_cost, switch_cost = flat[:, :, index[:, 0]], flat[:, :, index[:, 1]]
        keep_dst, switch_dst = self.dst[:, 0], self.dst[:, 1]
        for i in range(H, 0, -1):
            h[:, i] += outside[i - 1]
            nxt = h[:, i]
            np.minimum(keep_cost[:, i - 1] + nxt.take(keep_dst, axis=1),
                       switch_cost[:, i - 1] + nxt.take(switch_dst, axis=1), out=h[:, i - 1, :N])
        return h

    def trace(self, h: np.ndarray, costs: np.ndarray, starts: np.ndarray,
              prefer: np.ndarray | None = None) -> np.ndarray:
        """(M, nd, H): the least-cost plan of each table of :meth:`cost_to_go`; with
        ``prefer`` (M, nd, H; -1 = no preference), the plan that follows it as long as the
        bounds can still be kept from there (then the least-cost step back to it)."""
        M, nd = h.shape[0], len(self.graphs)
        m = np.arange(M)[:, None, None]
        j = np.arange(nd)[None, :, None]
        u = np.zeros((M, nd, self.H), dtype=int)
        s = np.broadcast_to(np.asarray(starts), (M, nd))
        for i in range(self.H):
            cls, dst = self.cls[s], self.dst[s]                          # (M, nd, 2)
            cand = costs[m, j, i, cls] + h[m, i + 1, dst]
            if prefer is not None:  # a step away from the preferred plan costs 1e12 more
                cand += 1e12 * (((cls != OFF) != prefer[:, :, i, None])
                                & (prefer[:, :, i, None] >= 0))
            second = cand[..., 1] < cand[..., 0]
            u[:, :, i] = np.where(second, cls[..., 1], cls[..., 0]) != OFF
            s = np.where(second, dst[..., 1], dst[..., 0])
        return u

    def objectives(self, plans: np.ndarray, u_prev: np.ndarray, costs: np.ndarray,
                   table: np.ndarray, z0: float, peak_cost: Callable[[np.ndarray], np.ndarray]
                   ) -> np.ndarray:
        """Energy plus peak cost of each relay plan of ``plans`` (P, nd, H); ``costs``:
        (nd, H, 3)."""
        u = np.asarray(plans) > 0.5
        first = np.broadcast_to(np.asarray(u_prev)[None, :, None] > 0.5, u[:, :, :1].shape)
        prev = np.concatenate([first, u[:, :, :-1]], axis=2)
        cls = np.where(u, np.where(prev, ON, START), OFF)                 # (P, nd, H)
        steps = np.arange(u.shape[2])
        energy = costs[np.arange(u.shape[1])[None, :, None], steps, cls].sum(axis=(1, 2))
        combos = np.einsum("j,pjh->ph", self.weights, cls)
        peak = np.maximum(z0, table[steps, combos].max(axis=1))
        return np.asarray(energy + peak_cost(peak), dtype=float)

    def solve(self, u_prev: np.ndarray, fixed: np.ndarray, costs: np.ndarray,
              c_lo: np.ndarray, c_hi: np.ndarray, table: np.ndarray,
              peak_cost: Callable[[np.ndarray], np.ndarray],
              prefer: np.ndarray | None = None, deadline: float = math.inf) -> DPResult:
        """The best plan and the proven bound. ``u_prev``, ``fixed``: each relay now and the
        steps its dwell still fixes it; ``costs`` (nd, H, 3): cost of each peripheral's
        step spent off, on, starting; ``c_lo``, ``c_hi`` (nd, H): bounds of the on-step
        counters; ``table`` (H, 3^nd): step peaks; ``peak_cost``: the J2 part of the
        objective, non-decreasing, elementwise on arrays; ``prefer`` (nd, H): a plan to start
        from (the previous one, shifted), made feasible if it is not.
        Past ``deadline`` (``time.perf_counter``) the best plan so far is returned with the
        bound proven up to then."""
        graphs, nd, H = self.graphs, len(self.graphs), self.H
        starts = self.offsets[:-1] + np.array(
            [g.initial(u_prev[j], fixed[j]) for j, g in enumerate(graphs)])
        z0 = float(table[:, 0].max())
        # caps: the levels from z0 to the previous plan's peak (all levels without one). A
        # better plan peaking higher must save energy: the unconstrained bound covers it.
        steps = np.arange(H)
        top = float(table.max()) if prefer is None else float(
            table[steps, self.weights @ self._classes(prefer, u_prev)].max())
        levels = np.unique(table[(table >= z0) & (table <= top)])
        caps = levels[np.unique(np.linspace(0, levels.size - 1, min(self.caps, levels.size))
                                .round().astype(int))] if levels.size else levels
        # per peripheral and class, the lowest step peak it allows (the others at their least)
        grid = table.reshape((H,) + (3,) * nd)
        least = np.stack([grid.min(axis=tuple(1 + k for k in range(nd) if k != j))
                          for j in range(nd)])                          # (nd, H, 3)
        tables = np.concatenate([np.where(least[None] <= caps[:, None, None, None] + 1e-9,
                                          costs[None], np.inf), costs[None]])
        hs = self.cost_to_go(tables, c_lo, c_hi)                      # (M + 1, H + 1, N + 1)
        if not np.isfinite(hs[-1, 0, starts]).all():
            return DPResult(None, math.inf, math.inf, 0)
        # incumbents: each cap's own least-energy plans put together, and the previous plan
        # kept as far as it stays feasible
        rows = np.flatnonzero(np.isfinite(hs[:, 0, starts]).all(axis=1))
        wish = np.full((rows.size, nd, H), -1)
        if prefer is not None:  # first: of equally good plans, the previous one is kept
            rows = np.append(rows[-1], rows)
            wish = np.concatenate([(np.asarray(prefer) > 0.5)[None].astype(int), wish])
        candidates = self.trace(hs[rows], tables[rows], starts, wish)
        values = self.objectives(candidates, u_prev, costs, table, z0, peak_cost)
        k = int(np.flatnonzero(values <= values.min() + 1e-12 * max(1.0, abs(values.min())))[0])
        best_u, best = candidates[k], float(values[k])
        # the least peak cost of a plan in cap k's bucket (above cap k - 1)
        floor_pc = peak_cost(np.concatenate([[z0], caps])).reshape((-1,) + (1,) * (nd + 1))
        search = Search(self, starts, costs, np.ascontiguousarray(hs.transpose(1, 0, 2)),
                        floor_pc, peak_cost(table), float(peak_cost(np.array(z0))),
                        1e-10 * max(1.0, abs(best)))
        # the exact search; if it grows large, a narrow beam first for a better incumbent
        # (which makes the exact search small), then the exact search again
        found = search.run(best, None, deadline, self.give_up)
        expanded = found.expanded
        if not found.complete and time.perf_counter() <= deadline:
            beam = search.run(best, self.beam, deadline)
            if beam.u is not None:
                best_u, best = beam.u, beam.value
            found = search.run(best, None, deadline)
            expanded += beam.expanded + found.expanded
        if found.u is not None:
            return DPResult(found.u, found.value, found.bound, expanded)
        return DPResult(best_u, best, min(best, found.bound), expanded)

    @staticmethod
    def _classes(u: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """(nd, H) local state class of each step of plan ``u``."""
        on = np.asarray(u) > 0.5
        prev = np.concatenate([np.asarray(u_prev)[:, None] > 0.5, on[:, :-1]], axis=1)
        return np.where(on, np.where(prev, ON, START), OFF)


class Outcome(NamedTuple):
    """One run of :class:`Search`."""

    u: np.ndarray | None    # the best plan below the threshold, or None
    value: float            # its objective, or the threshold
    bound: float            # lower bound of any plan below the threshold
    expanded: int           # partial plans kept
    complete: bool = False  # the search ran to its end (else: deadline or give_up)


@dataclass
class Search:
    """The forward search of :meth:`ScheduleDP.solve` over one horizon.

    ``hs`` (H + 1, M + 1, N + 1): the per-peripheral cost-to-go of each peak cap (the last
    one without a cap), ``floor_pc`` (M + 1, 1, ...): the least peak cost of a plan whose
    peak is above the previous cap, ``peak_costs`` (H, 3^nd): the peak cost of each step
    peak, ``pc0``: that of z0, ``tol``: the improvement that counts."""

    dp: ScheduleDP
    starts: np.ndarray
    costs: np.ndarray
    hs: np.ndarray
    floor_pc: np.ndarray
    peak_costs: np.ndarray
    pc0: float
    tol: float

    def run(self, best: float, beam: int | None, deadline: float,
            give_up: int | None = None) -> Outcome:
        """The best plan below ``best`` (None if there is none) and a lower bound of any plan
        below ``best`` (``best`` when the search is complete). With ``beam``, only that many
        partial plans (least bound first) are kept per step: a heuristic, proving nothing
        (bound -inf). With ``give_up``, the search stops (incomplete) when a step keeps more
        partial plans than that."""
        dp, costs, nd = self.dp, self.costs, len(self.dp.graphs)
        H, N, B = dp.H, dp.N, 2 ** nd
        S = self.starts[None, :]
        pc = np.array([self.pc0])
        g = np.zeros(1)
        trail: list[tuple[np.ndarray, np.ndarray]] = []  # per step: parent, combination
        expanded = 0
        # before any step: the least over the caps of the own cost-to-go plus peak cost
        lower = float((self.hs[0][:, self.starts].sum(axis=1) + self.floor_pc.ravel()).min())
        for i in range(H):
            if time.perf_counter() > deadline:
                return Outcome(None, best, lower if beam is None else -math.inf, expanded)
            K = S.shape[0]
            gn = g.reshape((K,) + (1,) * nd)
            combo: np.ndarray | int = 0
            key: np.ndarray | int = 0
            rest: np.ndarray | float = 0.0
            D, C = dp.dst[S], dp.cls[S]                                   # (K, nd, 2)
            R = self.hs[i + 1][:, D]                                      # (M + 1, K, nd, 2)
            for j in range(nd):
                axes = (K,) + (1,) * j + (2,) + (1,) * (nd - 1 - j)
                c = C[:, j].reshape(axes)
                gn = gn + costs[j, i][c]
                combo = combo + c * dp.weights[j]
                key = key * (N + 1) + D[:, j].reshape(axes)
                rest = rest + R[:, :, j].reshape((-1, *axes))
            pcn = np.maximum(pc.reshape((K,) + (1,) * nd), self.peak_costs[i][combo])
            lb = (gn + (rest + np.maximum(pcn, self.floor_pc)).min(axis=0)).ravel()
            keep = np.flatnonzero(lb < best - self.tol)
            if keep.size == 0:  # nothing left can beat ``best``
                return Outcome(None, best, best if beam is None else -math.inf, expanded, True)
            lower = float(lb[keep].min()) if beam is None else -math.inf
            keys = np.asarray(key).ravel()[keep]
            gk = np.asarray(gn).ravel()[keep]
            pk = pcn.ravel()[keep]
            order = np.lexsort((gk, pk, keys))
            ks, gs = keys[order], gk[order]
            first = np.empty(ks.size, dtype=bool)
            first[0] = True
            np.not_equal(ks[1:], ks[:-1], out=first[1:])
            # Pareto front of (peak cost, energy) per joint state: sorted by peak cost, a
            # partial plan stays if its energy is below that of every one before it in its
            # state (the shift by group keeps the running minimum within the group)
            shifted = gs - (np.cumsum(first) - 1) * (float(gs.max() - gs.min()) + 1.0)
            front = first.copy()
            front[1:] |= shifted[1:] < np.minimum.accumulate(shifted)[:-1] - self.tol
            chosen = order[front]
            if beam is not None and chosen.size > beam:
                chosen = chosen[np.argpartition(lb[keep[chosen]], beam)[:beam]]
            if give_up is not None and chosen.size > give_up:
                return Outcome(None, best, lower, expanded)
            S = (keys[chosen][:, None] // dp.strides) % (N + 1)
            pc, g = pk[chosen], gk[chosen]
            trail.append((keep[chosen] // B, np.asarray(combo).ravel()[keep[chosen]]))
            expanded += chosen.size
        total = g + pc
        k = int(np.argmin(total))
        value = float(total[k])
        if not value < best - self.tol:
            return Outcome(None, best, best if beam is None else -math.inf, expanded, True)
        u = np.zeros((nd, H), dtype=int)
        for i in range(H - 1, -1, -1):
            parent, combos = trail[i]
            u[:, i] = (combos[k] // dp.weights) % 3 != OFF
            k = int(parent[k])
        return Outcome(u, value, value if beam is None else -math.inf, expanded, True)
