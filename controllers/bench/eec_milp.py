"""The EEC's horizon problem as a MILP, solved by HiGHS through highspy.

:class:`EECMilp` is the general formulation and the reference of the schedule DP
(:mod:`hil.controllers.bench.eec_dp`); :mod:`hil.controllers.bench.eec_cvxpy` holds the direct
cvxpy formulation, the reference of the tests. The formulation:

* per peripheral j and step i: ``u`` (binary), start ``s`` and stop ``d`` (continuous in
  [0, 1], integral whenever ``u`` is): ``u_i - u_(i-1) = s_i - d_i``, ``sum(s over the last L
  steps) <= u_i``, ``sum(d over the last L steps) <= 1 - u_i`` (the tight min up/down form);
* J1 is linear in (u, s): its coefficients are the areas of the model responses, no rows;
* the levels are integer sums: ``q_j(i+1) = q_j(0) + alpha_j c_j(i) + eta_j sum_(k<=i) u_k``
  becomes bounds on an on-step counter ``c_i = c_(i-1) + u_i``, rounded inwards to integers;
* J2 by levels instead of one epigraph row per sample: each step's peak is a function of the
  peripherals' local states (off / on / starting; 3^n combinations, 9 for P1 and P2), so the
  step contributes one row per combination that reaches a new level, ``sum(states) - (n - 1)
  <= lambda_k``, with monotone level binaries ``lambda_1 >= lambda_2 >= ...`` whose costs add
  up to the peak. Exact at every integer point (brute force and the cvxpy reference agree in
  the tests), about 140 rows instead of 2800, and branching on a level is a strong decision.
* the static rows are built once; each solve assembles bounds and J2 rows from arrays and
  passes the model to the same HiGHS instance, with the previous plan, shifted and repaired,
  as the starting solution.
"""

from __future__ import annotations

import math
import time
from typing import TypeVar

import highspy
import numpy as np

from hil.controllers.bench.eec_costs import HorizonCosts
from hil.controllers.bench.eec_repair import repair
from hil.controllers.bench.eec_settings import SolveResult
from hil.controllers.highs import silent_highs

INF = highspy.kHighsInf
Index = TypeVar("Index", int, np.ndarray)  # one column (int) or many (array)
# HiGHS options, measured on closed-loop runs (benchmarks/eec.py): on these small models the
# MIP presolve (probing) and the feasibility-jump heuristic cost more than they save
SOLVER_OPTIONS: tuple[tuple[str, bool | int | float | str], ...] = (
    ("output_flag", False), ("threads", 1), ("presolve", "off"),
    ("mip_heuristic_run_feasibility_jump", False),
)


class EECMilp:
    """The MILP of one horizon: fixed structure built once, bounds and J2 rows per solve."""

    def __init__(self, horizon: HorizonCosts) -> None:
        self.horizon = horizon
        self.nd, self.H = horizon.nd, horizon.H
        self.n_static_cols = 4 * self.nd * self.H
        self._build_static()
        self.highs = silent_highs()
        for option, value in (*SOLVER_OPTIONS,
                              ("mip_rel_gap", float(horizon.settings.mip_rel_gap))):
            self.highs.setOptionValue(option, value)

    # -- indices ---------------------------------------------------------------------------
    # per peripheral j four blocks of H columns: u (relay), s (start), d (stop), c (on-steps
    # so far: c_i = c_(i-1) + u_i, whose bounds carry the resource levels); then the level
    # binaries lambda_k of J2, whose number changes from solve to solve.
    def col_u(self, j: int, i: Index) -> Index:
        return j * 4 * self.H + i

    def col_s(self, j: int, i: Index) -> Index:
        return j * 4 * self.H + self.H + i

    def col_d(self, j: int, i: Index) -> Index:
        return j * 4 * self.H + 2 * self.H + i

    def col_c(self, j: int, i: Index) -> Index:
        return j * 4 * self.H + 3 * self.H + i

    # -- the fixed part --------------------------------------------------------------------
    def _build_static(self) -> None:
        H, nd, horizon = self.H, self.nd, self.horizon
        r, c, v = [], [], []
        lo: list[float] = []
        hi: list[float] = []

        def row(entries: list[tuple[int, float]], low: float, high: float) -> int:
            n = len(lo)
            for col, val in entries:
                r.append(n)
                c.append(col)
                v.append(val)
            lo.append(low)
            hi.append(high)
            return n

        self.row_trans = []
        for j in range(nd):
            for i in range(H):  # u_i - u_(i-1) - s_i + d_i = (u_prev if i == 0)
                entries = [(self.col_u(j, i), 1.0), (self.col_s(j, i), -1.0),
                           (self.col_d(j, i), 1.0)]
                if i > 0:
                    entries.append((self.col_u(j, i - 1), -1.0))
                self.row_trans.append(row(entries, 0.0, 0.0))
            L = horizon.dwell_steps[j]
            for i in range(H if L > 1 else 0):  # minimum up and down time
                window = range(max(0, i - L + 1), i + 1)
                row([(self.col_s(j, k), 1.0) for k in window] + [(self.col_u(j, i), -1.0)],
                    -INF, 0.0)
                row([(self.col_d(j, k), 1.0) for k in window] + [(self.col_u(j, i), 1.0)],
                    -INF, 1.0)
            for i in range(H):  # c_i - c_(i-1) - u_i = 0
                entries = [(self.col_c(j, i), 1.0), (self.col_u(j, i), -1.0)]
                if i > 0:
                    entries.append((self.col_c(j, i - 1), -1.0))
                row(entries, 0.0, 0.0)
        self.static_rows = (np.array(r), np.array(c), np.array(v))
        self.static_row_lo, self.static_row_hi = np.array(lo), np.array(hi)
        n = self.n_static_cols
        cost = np.zeros(n)
        upper = np.ones(n)
        integer = np.zeros(n, dtype=bool)
        for j in range(nd):
            idx = np.arange(H)
            cost[self.col_u(j, idx)] = horizon.w1 * horizon.area_u[j]
            cost[self.col_s(j, idx)] = horizon.start_cost[j]
            integer[self.col_u(j, idx)] = True
            upper[self.col_c(j, idx)] = idx + 1
        self.static_cost, self.static_upper, self.static_integer = cost, upper, integer

    def level_rows(self, table: np.ndarray) -> tuple[float, np.ndarray, list[tuple]]:
        """(Z0, levels, rows): the peak with every peripheral off (a lower bound of J2), the
        higher peak values that some state combination reaches, and for each step and
        combination that reaches a new level, (step, combination, level index)."""
        z0 = float(table[:, 0].max())
        candidate = table > z0
        for k, lower in enumerate(self.horizon.lower_neighbours):
            for kk in lower:  # implied by a lower combination that reaches the same level
                candidate[:, k] &= table[:, kk] < table[:, k]
        levels = np.unique(table[candidate])
        steps, combos = np.nonzero(candidate)
        kappa = np.searchsorted(levels, table[steps, combos])
        return z0, levels, list(zip(steps.tolist(), combos.tolist(), kappa.tolist(),
                                    strict=True))

    # -- per solve -------------------------------------------------------------------------
    def solve(self, t0: float, table: np.ndarray, u_prev: np.ndarray, fixed_steps: np.ndarray,
              c_lo: np.ndarray, c_hi: np.ndarray, warm_u: np.ndarray | None, budget: float
              ) -> SolveResult:
        """The plan of the step peaks ``table`` (:meth:`HorizonCosts.peak_table`) within the
        on-step bounds ``c_lo``, ``c_hi``, started ``t0`` (``time.perf_counter()``).
        ``fixed_steps[j]``: steps u_j must keep ``u_prev[j]`` (the dwell still running);
        ``warm_u`` (devices x H): a candidate plan, the starting solution once
        :func:`~hil.controllers.bench.eec_repair.repair` made it feasible; ``budget``: the
        solver's time limit (s)."""
        H, nd = self.H, self.nd
        z0, levels, pattern = self.level_rows(table)
        K = levels.size
        self._pass(*self._columns(u_prev, fixed_steps, c_lo, c_hi, z0, levels),
                   *self._rows(u_prev, c_lo, K, pattern))
        h = self.highs
        warm = False
        if warm_u is not None:
            plan = repair(self.horizon, np.asarray(warm_u, float), u_prev, fixed_steps, c_lo,
                          c_hi, table)
            if plan is not None:
                x = self.point(plan, u_prev, table, z0, levels)
                h.setSolution(x.size, np.arange(x.size, dtype=np.int32), x)
                warm = True
        # per run (highspy 1.15 restarts the clock at every run; older 1.x did not)
        h.setOptionValue("time_limit", float(budget))
        h.run()
        status = h.getModelStatus()
        info = h.getInfo()
        has_solution = info.primal_solution_status == 2  # kSolutionStatusFeasible
        name = {highspy.HighsModelStatus.kOptimal: "optimal",
                highspy.HighsModelStatus.kTimeLimit: "time_limit",
                highspy.HighsModelStatus.kInfeasible: "infeasible"}.get(
                    status, h.modelStatusToString(status))
        solve_ms = (time.perf_counter() - t0) * 1e3
        if not has_solution:
            return SolveResult(name if name != "optimal" else "no solution", None, math.nan,
                               math.nan, solve_ms, len(pattern), warm, K)
        col = np.asarray(h.getSolution().col_value)
        u = np.rint(np.array([col[self.col_u(j, np.arange(H))] for j in range(nd)]))
        steps = np.diff(np.concatenate([[z0], levels]))
        peak = z0 + float(np.dot(np.rint(col[self.n_static_cols:]), steps))
        # the full J (eq. 4 plus the limit term), without the constant machining area
        objective = float(info.objective_function_value) + self.horizon.peak_cost(z0)
        return SolveResult(name, u.astype(int), objective, peak, solve_ms, len(pattern), warm, K,
                           gap=float(info.mip_gap), nodes=int(info.mip_node_count),
                           bound=float(info.mip_dual_bound) + self.horizon.peak_cost(z0))

    def _columns(self, u_prev: np.ndarray, fixed_steps: np.ndarray, c_lo: np.ndarray,
                 c_hi: np.ndarray, z0: float, levels: np.ndarray) -> tuple[np.ndarray, ...]:
        """(cost, lower, upper, integer) of every column: the running dwell fixes the first
        relay steps, the levels bound the on-step counters, the J2 levels cost their rise."""
        H, K = self.H, levels.size
        lower = np.zeros(self.n_static_cols + K)
        upper = np.concatenate([self.static_upper, np.ones(K)])
        for j in range(self.nd):
            idx = self.col_u(j, np.arange(int(min(fixed_steps[j], H))))
            lower[idx] = upper[idx] = float(u_prev[j])
            cols = self.col_c(j, np.arange(H))
            lower[cols], upper[cols] = c_lo[j], c_hi[j]
        horizon = self.horizon
        previous = np.concatenate([[z0], levels[:-1]])
        rise = horizon.w2 * (levels - previous)
        if horizon.settings.limit_va is not None:
            lim = float(horizon.settings.limit_va)
            rise += horizon.w_limit * (np.maximum(levels, lim) - np.maximum(previous, lim))
        cost = np.concatenate([self.static_cost, rise])
        integer = np.concatenate([self.static_integer, np.ones(K, dtype=bool)])
        return cost, lower, upper, integer

    def _rows(self, u_prev: np.ndarray, c_lo: np.ndarray, K: int,
              pattern: list[tuple[int, int, int]]) -> tuple[np.ndarray, ...]:
        """(row_lo, row_hi, rows, cols, values): the static rows (step 0 bound to the relay
        state), the start cuts, the level chain and the J2 pattern rows."""
        H, nd = self.H, self.nd
        row_lo, row_hi = self.static_row_lo.copy(), self.static_row_hi.copy()
        for j in range(nd):
            row_lo[self.row_trans[j * H]] = row_hi[self.row_trans[j * H]] = float(u_prev[j])
        sr, sc, sv = self.static_rows
        rr, cc, vv = [sr], [sc], [sv]
        # a relay that is off and must have produced by step t starts by step t
        cut_lo: list[float] = []
        for j in range(nd):
            need = np.nonzero(c_lo[j] >= 1)[0]
            if u_prev[j] < 0.5 and need.size:
                window = np.arange(need[0] + 1)
                rr.append(np.full(window.size, row_lo.size + len(cut_lo)))
                cc.append(self.col_s(j, window))
                vv.append(np.ones(window.size))
                cut_lo.append(1.0)
        row_lo = np.concatenate([row_lo, cut_lo])
        row_hi = np.concatenate([row_hi, np.full(len(cut_lo), INF)])
        n0 = row_lo.size
        lam = self.n_static_cols + np.arange(K)
        if K > 1:  # lambda_k <= lambda_(k-1)
            chain = n0 + np.arange(K - 1)
            rr += [chain, chain]
            cc += [lam[1:], lam[:-1]]
            vv += [np.ones(K - 1), -np.ones(K - 1)]
        n1 = n0 + max(K - 1, 0)
        p_rows, p_cols, p_vals, p_hi = [], [], [], []
        for k, (i, combo, level) in enumerate(pattern):
            for j, state in enumerate(self.horizon.states[combo]):
                if state:
                    p_rows.append(n1 + k)
                    p_cols.append(self.col_u(j, i) if state == 1 else self.col_s(j, i))
                    p_vals.append(1.0)
            p_rows.append(n1 + k)
            p_cols.append(lam[level])
            p_vals.append(-1.0)
            p_hi.append(float(self.horizon.n_on[combo] - 1))
        rr.append(np.array(p_rows, dtype=int))
        cc.append(np.array(p_cols, dtype=int))
        vv.append(np.array(p_vals))
        row_lo = np.concatenate([row_lo, np.full(n1 - n0 + len(pattern), -INF)])
        row_hi = np.concatenate([row_hi, np.zeros(n1 - n0), np.array(p_hi)])
        return row_lo, row_hi, np.concatenate(rr), np.concatenate(cc), np.concatenate(vv)

    def _pass(self, cost: np.ndarray, lower: np.ndarray, upper: np.ndarray,
              integer: np.ndarray, row_lo: np.ndarray, row_hi: np.ndarray, r: np.ndarray,
              c: np.ndarray, v: np.ndarray) -> None:
        """Hand the assembled model to the HiGHS instance (rowwise matrix)."""
        n = cost.size
        order = np.lexsort((c, r))
        r, c, v = r[order], c[order], v[order]
        lp = highspy.HighsLp()
        lp.num_col_, lp.num_row_ = n, row_lo.size
        lp.col_cost_, lp.col_lower_, lp.col_upper_ = cost, lower, upper
        lp.row_lower_, lp.row_upper_ = row_lo, row_hi
        lp.a_matrix_.format_ = highspy.MatrixFormat.kRowwise
        lp.a_matrix_.start_ = np.searchsorted(r, np.arange(row_lo.size + 1)).astype(np.int32)
        lp.a_matrix_.index_ = c.astype(np.int32)
        lp.a_matrix_.value_ = v
        lp.integrality_ = [self._integer if flag else self._continuous for flag in integer]
        self.highs.passModel(lp)

    _integer = highspy.HighsVarType.kInteger
    _continuous = highspy.HighsVarType.kContinuous

    def point(self, u: np.ndarray, u_prev: np.ndarray, table: np.ndarray, z0: float,
              levels: np.ndarray) -> np.ndarray:
        """The full column vector of relay plan ``u`` (levels switched on up to its peak)."""
        H = self.H
        x = np.zeros(self.n_static_cols + levels.size)
        for j in range(self.nd):
            uj = np.asarray(u[j], float)
            diff = np.diff(np.concatenate([[u_prev[j]], uj]))
            x[self.col_u(j, np.arange(H))] = uj
            x[self.col_s(j, np.arange(H))] = np.clip(diff, 0, None)
            x[self.col_d(j, np.arange(H))] = np.clip(-diff, 0, None)
            x[self.col_c(j, np.arange(H))] = np.cumsum(uj)
        peak = table[np.arange(H), self.horizon.states_of(u, u_prev)].max()
        x[self.n_static_cols:] = (levels <= peak + 1e-9) & (peak > z0)
        return x
