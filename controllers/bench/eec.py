"""The energy-efficiency controller (EEC) of the energy paper: a receding-horizon MILP.

Every decision step (1 s) it chooses the on/off plan of the peripherals over ``H_p`` steps
minimising ``J = gamma1 n1 J1 + gamma2 n2 J2`` (eq. 4): J1 the area under the predicted total
apparent power, J2 its highest point, subject to the resource relations and bounds (eq. 10,
Table I), the minimum on/off dwell (including the dwell already running) and the power models
(:mod:`hil.controllers.bench.prediction`, 0.01 s grid: the inrush is resolved inside each step). It
applies the first step (``H_s = 1``) or the whole plan (``H_s = H_p``). Beyond the paper:

* a terminal condition ``q_j(H_p) >= q_j(0)`` (``terminal = "hold"``; ``q_j(0)`` the level of
  Table I the machine starts with): without it an energy-minimising plan drains every level
  to its minimum at the horizon end, so both motors must start together later. (Anchored to
  the level *now* instead, it ratchets the levels up under a receding horizon: whatever a
  plan produces early raises the next plan's target.) A start in the last steps is charged
  the energy of its minimum on time beyond the horizon, or plans would start motors there.
* a contracted power limit: the part of the peak above ``limit_va`` costs ``limit_weight``
  times more. This is where the estimated disturbance matters: an offset added to every
  predicted point shifts J1 and J2 by constants and cannot change the plan, but it moves the
  plan against the limit.
* an infeasible or failed solve falls back to the hysteresis rule for that step.

Formulation (HiGHS through highspy; :mod:`hil.controllers.bench.eec_cvxpy` holds the direct cvxpy
formulation, the reference of the tests):

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

Solve time: the LP relaxation stays weak when the plan must trade peak against energy (it
spreads fractional "thin" runs over the horizon), so HiGHS proves some instants only after
0.3-0.7 s of root cuts and branching. The default ``solver = "dp"``
(:mod:`hil.controllers.bench.eec_dp`) finds the same optimum exactly by a pruned dynamic program
over the relay schedules (bounds from per-peripheral cost-to-go under a few peak caps,
dominance, the previous plan and a beam search as incumbents), in a few ms at H_p = T; the
MILP stays as the general formulation and the reference. ``time_limit_s`` is a safety net:
at the limit the best plan found is used (status ``time_limit``, its gap recorded). ``nodes``
of a DP solve counts the partial plans its searches kept.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TypeVar

import highspy
import numpy as np

from hil.controllers.base import BenchObservation
from hil.controllers.bench.bc import hysteresis_rule
from hil.controllers.bench.eec_choices import SOLVERS, TERMINALS
from hil.controllers.bench.eec_dp import DeviceGraph, ScheduleDP
from hil.controllers.bench.kalman import BenchKalman, KalmanSettings
from hil.controllers.bench.prediction import BenchEstimate, BenchModels, HorizonPrediction
from hil.controllers.bench.problem import BenchProblem, DwellClock
from hil.controllers.highs import silent_highs

INF = highspy.kHighsInf
Index = TypeVar("Index", int, np.ndarray)  # one column (int) or many (array)
# HiGHS options, measured on closed-loop runs (benchmarks/eec.py): on these small models the
# MIP presolve (probing) and the feasibility-jump heuristic cost more than they save
SOLVER_OPTIONS: tuple[tuple[str, bool | int | float | str], ...] = (
    ("output_flag", False), ("threads", 1), ("presolve", "off"),
    ("mip_heuristic_run_feasibility_jump", False),
)


@dataclass(frozen=True)
class EECSettings:
    """Tuning of the EEC (``[eec]`` of ``hil/configs/eec.toml`` documents each)."""

    hp_steps: int = 28
    hs_steps: int = 1
    step_s: float = 1.0
    gamma1: float = 0.9
    gamma2: float = 0.1
    gamma3: float = 0.0        # cost of one switch-on (relay wear), in units of J
    terminal: str = "hold"
    limit_va: float | None = None
    limit_weight: float = 10.0
    peak_resolution_va: float = 1.0
    time_limit_s: float = 1.0
    mip_rel_gap: float = 1e-4
    solver: str = "dp"         # "dp": exact schedule DP (2 peripherals); "milp": HiGHS

    def __post_init__(self) -> None:
        if self.hp_steps < 1 or self.hs_steps < 1 or self.hs_steps > self.hp_steps:
            raise ValueError(f"need 1 <= H_s <= H_p, got H_s = {self.hs_steps}, "
                             f"H_p = {self.hp_steps}")
        if self.terminal not in TERMINALS:
            raise ValueError(f"terminal must be one of {TERMINALS}, got {self.terminal!r}")
        if self.gamma1 < 0 or self.gamma2 < 0 or self.gamma1 + self.gamma2 <= 0:
            raise ValueError("gamma1, gamma2 must be >= 0 and not both 0")
        if self.gamma3 < 0:
            raise ValueError(f"gamma3 must be >= 0, got {self.gamma3}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {self.solver!r}")


@dataclass
class SolveResult:
    status: str                # "optimal", "time_limit", "infeasible", "error: ..."
    u: np.ndarray | None       # devices x H, 0/1
    objective: float
    peak_va: float             # z: the plan's predicted highest point
    solve_ms: float
    rows: int                  # J2 pattern rows
    warm_start: bool
    levels: int = 0            # J2 level binaries
    gap: float = 0.0           # relative MIP gap at the end (0: proven optimal)
    nodes: int = 0             # branch-and-bound nodes (MILP) or partial plans kept (DP)
    bound: float = math.nan    # proven lower bound of the objective


@dataclass
class Plan:
    """One solved plan, as recorded to ``/eec/plan``."""

    t_s: float
    u: np.ndarray              # devices x H
    q: np.ndarray              # resources x (H + 1): predicted levels
    power_va: np.ndarray       # predicted total VA, one value per step (max within the step)
    peak_va: float
    energy_vas: float
    objective: float
    status: str
    solve_ms: float
    rows: int
    gap: float = 0.0
    nodes: int = 0
    bound: float = math.nan


@dataclass
class Decision:
    relays: dict[str, bool]
    plan: Plan | None = None
    solve: SolveResult | None = None
    fallback: str | None = None     # why the hysteresis rule decided this step
    events: list[tuple[str, str]] = field(default_factory=list)


class EECMilp:
    """The MILP of one horizon: fixed structure built once, bounds and J2 rows per solve."""

    def __init__(self, prediction: HorizonPrediction, problem: BenchProblem,
                 settings: EECSettings) -> None:
        self.p = prediction
        self.problem = problem
        self.settings = settings
        self.nd = len(problem.peripherals)
        self.H = prediction.steps
        self.n_static_cols = 4 * self.nd * self.H
        self.dwell_steps = [
            max(0, math.ceil(problem.dwell_s[name] / settings.step_s - 1e-9))
            for name in problem.peripherals
        ]
        n1, n2 = prediction.normalisation()
        self.w1 = settings.gamma1 * n1
        self.w2 = settings.gamma2 * n2
        # 1 VA above the contracted limit costs limit_weight times 1 VA of peak
        self.w_limit = settings.limit_weight * self.w2
        # J1 coefficients (VA s): the area each decision adds over the horizon. A start near
        # the end commits the relay beyond the horizon for its minimum on time: that energy is
        # charged too, or every plan would start motors at its very end.
        self.area_u, area_s = prediction.energy_costs()
        idx = np.arange(self.H)
        self.area_s = area_s + np.array([
            np.clip(self.dwell_steps[j] - (self.H - idx), 0, None) * settings.step_s
            * prediction.models.devices[name].steady_va
            for j, name in enumerate(problem.peripherals)])
        # what one switch-on costs: its energy and the relay wear (gamma3)
        self.start_cost = self.w1 * self.area_s + settings.gamma3
        self.Gu, self.Gs = prediction.dense()
        self._consumption: dict[tuple[str, float], np.ndarray] = {}
        self._prepare_patterns()
        self._build_static()
        self.dp = ScheduleDP([DeviceGraph(self.H, L, L) for L in self.dwell_steps]) \
            if settings.solver == "dp" else None
        # (peripherals, H, 3): the cost of each step spent off, on, starting
        self.class_costs = np.stack([np.stack([np.zeros(self.H), self.w1 * self.area_u[j],
                                               self.w1 * self.area_u[j] + self.start_cost[j]],
                                              axis=1) for j in range(self.nd)])
        self.highs = silent_highs()
        for option, value in (*SOLVER_OPTIONS, ("mip_rel_gap", float(settings.mip_rel_gap))):
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
        H, nd = self.H, self.nd
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
            L = self.dwell_steps[j]
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
            cost[self.col_u(j, idx)] = self.w1 * self.area_u[j]
            cost[self.col_s(j, idx)] = self.start_cost[j]
            integer[self.col_u(j, idx)] = True
            upper[self.col_c(j, idx)] = idx + 1
        self.static_cost, self.static_upper, self.static_integer = cost, upper, integer

    def _prepare_patterns(self) -> None:
        """Each step's peak as a function of the peripherals' local states.

        The state of peripheral j in step i is off (u = 0), on (u = 1, s = 0) or starting
        (s = 1); its power over the step's samples is 0, the steady response, or the steady
        response plus the inrush. The other coefficients (responses reaching into later
        steps, feedthrough from the next step) are small and bounded by their largest
        positive values: an inrush still decaying from a start in an earlier step only while
        the relay is on (the dwell keeps it on), the rest in any state. An upper bound, exact
        when they are 0 (models whose transients end within a step).
        """
        coef = self.p.coef  # (spd, nd, kind, lag index), lag index 1 = same step
        nd = self.nd
        steady = coef[:, :, 0, 1].T                       # (nd, spd)
        start = steady + coef[:, :, 1, 1].T
        late = np.clip(coef, 0, None).max(axis=0)         # (nd, kind, lag index)
        late[:, :, 1] = 0.0
        any_state = late[:, 0, :].sum(axis=1)             # relay response tails, next step
        any_state += late[:, 1, 0]                        # start feedthrough from next step
        when_on = late[:, 1, 2:].sum(axis=1)              # inrush tails of earlier starts
        # the most the step peaks can overestimate the predicted power (0 for models whose
        # transients end within one step)
        self.peak_overestimate_va = float(np.sum(any_state + when_on))
        zero = np.zeros_like(steady)
        self.contrib = np.stack([zero + any_state[:, None],
                                 steady + (any_state + when_on)[:, None],
                                 start + (any_state + when_on)[:, None]], axis=1)
        states = np.array(list(itertools.product(range(3), repeat=nd)))  # (combos, nd)
        self.states = states
        self.n_on = (states > 0).sum(axis=1)
        index = {tuple(st): k for k, st in enumerate(states)}
        self.lower_neighbours = [
            [index[tuple(st - np.eye(nd, dtype=int)[j])] for j in range(nd) if st[j] > 0]
            for st in states
        ]
        # (combos, spd): the peripherals' power of each combination of states
        self.combo_power = np.zeros((len(states), coef.shape[0]))
        for k, st in enumerate(states):
            for j in range(nd):
                self.combo_power[k] += self.contrib[j, st[j]]

    def peak_table(self, free: np.ndarray) -> np.ndarray:
        """(H, combos): the highest predicted VA of each step for each combination of states
        (rounded up to ``peak_resolution_va``)."""
        F = free.reshape(self.H, -1)
        table = np.max(F[:, None, :] + self.combo_power[None], axis=2)
        res = self.settings.peak_resolution_va
        return np.ceil(table / res - 1e-9) * res if res > 0 else table

    def level_rows(self, table: np.ndarray) -> tuple[float, np.ndarray, list[tuple]]:
        """(Z0, levels, rows): the peak with every peripheral off (a lower bound of J2), the
        higher peak values that some state combination reaches, and for each step and
        combination that reaches a new level, (step, combination, level index)."""
        z0 = float(table[:, 0].max())
        candidate = table > z0
        for k, lower in enumerate(self.lower_neighbours):
            for kk in lower:  # implied by a lower combination that reaches the same level
                candidate[:, k] &= table[:, kk] < table[:, k]
        levels = np.unique(table[candidate])
        steps, combos = np.nonzero(candidate)
        kappa = np.searchsorted(levels, table[steps, combos])
        return z0, levels, list(zip(steps.tolist(), combos.tolist(), kappa.tolist(),
                                    strict=True))

    # -- per solve -------------------------------------------------------------------------
    def level_bounds(self, q0: np.ndarray, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Integer bounds (resources x H) on the cumulative on-steps of each supplier."""
        H, step = self.H, self.settings.step_s
        lo = np.empty((self.nd, H))
        hi = np.empty((self.nd, H))
        for j, res in enumerate(self.problem.resources):
            drain = res.alpha * np.cumsum(self.consumption(res.consumer, t_s))
            gain = res.eta * step
            lo[j] = np.ceil((res.q_min - q0[j] - drain) / gain - 1e-7)
            hi[j] = np.floor((res.q_max - q0[j] - drain) / gain + 1e-7)
            if self.settings.terminal == "hold":
                target = min(res.q0, res.q_max - gain)
                lo[j, -1] = max(lo[j, -1], math.ceil((target - q0[j] - drain[-1]) / gain - 1e-7))
        return lo, hi

    def consumption(self, relay: str, t_s: float) -> np.ndarray:
        """Seconds the consumer ``relay`` is on in each step of the horizon from ``t_s``."""
        step, seq = self.settings.step_s, self.problem.sequence
        key = (relay, round(t_s % seq.period_s, 9))  # the sequence is periodic
        if key not in self._consumption:
            if len(self._consumption) > 4096:
                self._consumption.clear()
            self._consumption[key] = np.array([
                seq.on_fraction(relay, t_s + i * step, t_s + (i + 1) * step)
                for i in range(self.H)]) * step
        return self._consumption[key]

    def solve(self, free: np.ndarray, u_prev: np.ndarray, fixed_steps: np.ndarray,
              q0: np.ndarray, t_s: float, warm_u: np.ndarray | None = None,
              budget_s: float | None = None) -> SolveResult:
        """Solve for the plan. ``fixed_steps[j]``: steps u_j must keep ``u_prev[j]`` (the dwell
        still running); ``q0``: levels now; ``warm_u`` (devices x H): a candidate plan (made
        feasible by :meth:`repair` if it can be); ``budget_s``: solver time limit (default
        the settings' ``time_limit_s``)."""
        t0 = time.perf_counter()
        H, nd = self.H, self.nd
        qlo, qhi = self.level_bounds(q0, t_s)
        c_lo, c_hi = np.maximum(qlo, 0.0), np.minimum(qhi, np.arange(H) + 1.0)
        if np.any(c_lo > c_hi):
            return SolveResult("infeasible", None, math.nan, math.nan,
                               (time.perf_counter() - t0) * 1e3, 0, False)
        table = self.peak_table(free)
        budget = self.settings.time_limit_s if budget_s is None else budget_s
        if self.dp is not None:
            return self._solve_dp(t0, table, u_prev, fixed_steps, c_lo, c_hi, warm_u, budget)
        z0, levels, pattern = self.level_rows(table)
        K = levels.size
        self._pass(*self._columns(u_prev, fixed_steps, c_lo, c_hi, z0, levels),
                   *self._rows(u_prev, c_lo, K, pattern))
        h = self.highs
        warm = False
        if warm_u is not None:
            plan = self.repair(np.asarray(warm_u, float), u_prev, fixed_steps, c_lo, c_hi,
                               table)
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
        objective = float(info.objective_function_value) + self.peak_cost(z0)
        return SolveResult(name, u.astype(int), objective, peak, solve_ms, len(pattern), warm, K,
                           gap=float(info.mip_gap), nodes=int(info.mip_node_count),
                           bound=float(info.mip_dual_bound) + self.peak_cost(z0))

    def _solve_dp(self, t0: float, table: np.ndarray, u_prev: np.ndarray,
                  fixed_steps: np.ndarray, c_lo: np.ndarray, c_hi: np.ndarray,
                  warm_u: np.ndarray | None, budget: float) -> SolveResult:
        """The same optimum by the schedule DP (:mod:`~hil.controllers.bench.eec_dp`);
        the previous plan (made feasible) is an incumbent, ``budget`` a safety net (status
        ``time_limit``)."""
        assert self.dp is not None
        z0 = float(table[:, 0].max())
        found = self.dp.solve(u_prev, fixed_steps, self.class_costs, c_lo, c_hi, table,
                              self.peak_costs, warm_u, t0 + budget)
        solve_ms = (time.perf_counter() - t0) * 1e3
        proven = found.bound >= found.objective
        if found.u is None:
            return SolveResult("infeasible", None, math.nan, math.nan, solve_ms, 0, False)
        u = found.u.astype(int)
        peak = max(z0, float(table[np.arange(self.H), self.states_of(u, u_prev)].max()))
        gap = 0.0 if proven else (found.objective - found.bound) / max(abs(found.objective),
                                                                       1e-12)
        return SolveResult("optimal" if proven else "time_limit", u, found.objective, peak,
                           solve_ms, 0, warm_u is not None, gap=gap, nodes=found.expanded,
                           bound=found.bound)

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
        previous = np.concatenate([[z0], levels[:-1]])
        rise = self.w2 * (levels - previous)
        if self.settings.limit_va is not None:
            lim = float(self.settings.limit_va)
            rise += self.w_limit * (np.maximum(levels, lim) - np.maximum(previous, lim))
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
            for j, state in enumerate(self.states[combo]):
                if state:
                    p_rows.append(n1 + k)
                    p_cols.append(self.col_u(j, i) if state == 1 else self.col_s(j, i))
                    p_vals.append(1.0)
            p_rows.append(n1 + k)
            p_cols.append(lam[level])
            p_vals.append(-1.0)
            p_hi.append(float(self.n_on[combo] - 1))
        rr.append(np.array(p_rows, dtype=int))
        cc.append(np.array(p_cols, dtype=int))
        vv.append(np.array(p_vals))
        row_lo = np.concatenate([row_lo, np.full(n1 - n0 + len(pattern), -INF)])
        row_hi = np.concatenate([row_hi, np.zeros(n1 - n0), np.array(p_hi)])
        return row_lo, row_hi, np.concatenate(rr), np.concatenate(cc), np.concatenate(vv)

    def peak_costs(self, peaks: np.ndarray) -> np.ndarray:
        """:meth:`peak_cost` of each of ``peaks``."""
        cost = self.w2 * peaks
        if self.settings.limit_va is not None:
            cost = cost + self.w_limit * np.maximum(0.0, peaks - float(self.settings.limit_va))
        return cost

    def peak_cost(self, peak: float) -> float:
        """w2 * peak plus the limit term for ``peak``."""
        cost = self.w2 * peak
        if self.settings.limit_va is not None:
            cost += self.w_limit * max(0.0, peak - float(self.settings.limit_va))
        return cost

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

    def feasible(self, u: np.ndarray, u_prev: np.ndarray, fixed_steps: np.ndarray,
                 c_lo: np.ndarray, c_hi: np.ndarray) -> bool:
        """Whether relay plan ``u`` keeps the dwell (running one included) and the levels."""
        return all(self._device_feasible(j, u[j], u_prev, fixed_steps, c_lo, c_hi)
                   for j in range(self.nd))

    def _device_feasible(self, j: int, uj: np.ndarray, u_prev: np.ndarray,
                         fixed_steps: np.ndarray, c_lo: np.ndarray, c_hi: np.ndarray) -> bool:
        changes = np.nonzero(np.diff(np.concatenate([[u_prev[j]], uj])))[0]
        if changes.size and changes[0] < min(fixed_steps[j], self.H):
            return False
        if np.any(np.diff(changes) < self.dwell_steps[j]):
            return False
        c = np.cumsum(uj)
        return bool(np.all(c >= c_lo[j] - 1e-9) and np.all(c <= c_hi[j] + 1e-9))

    def repair(self, u: np.ndarray, u_prev: np.ndarray, fixed_steps: np.ndarray,
               c_lo: np.ndarray, c_hi: np.ndarray, table: np.ndarray | None = None
               ) -> np.ndarray | None:
        """The candidate plan made feasible, or None.

        A peripheral whose part breaks its dwell or levels (a plan shifted by one step
        usually lacks production in its new last step) gets one more run: every run of the
        minimum length and every run to the horizon end is tried, and the feasible one with
        the least cost (energy plus peak, ``table`` from :meth:`peak_table`) is kept; without
        a table, the shortest final run.
        """
        u = u.copy()
        H = self.H
        for j in range(self.nd):
            if self._device_feasible(j, u[j], u_prev, fixed_steps, c_lo, c_hi):
                continue
            candidates = []
            for a in range(H - 1, -1, -1):
                for end in {H, min(H, a + self.dwell_steps[j])}:
                    trial = u[j].copy()
                    trial[a:end] = 1.0
                    if self._device_feasible(j, trial, u_prev, fixed_steps, c_lo, c_hi):
                        candidates.append(trial)
                if candidates and table is None:
                    break
            if not candidates:
                return None
            u[j] = candidates[int(np.argmin(self.costs(u, j, np.array(candidates), u_prev,
                                                       table)))] if table is not None \
                else candidates[0]
        return u

    def costs(self, u: np.ndarray, j: int, rows: np.ndarray, u_prev: np.ndarray,
              table: np.ndarray) -> np.ndarray:
        """Objective of plan ``u`` with peripheral j's part replaced by each of ``rows``."""
        prev = np.concatenate([np.full((rows.shape[0], 1), u_prev[j]), rows[:, :-1]], axis=1)
        starts = np.clip(rows - prev, 0, None)
        cost = self.w1 * (rows @ self.area_u[j]) + starts @ self.start_cost[j]
        others = np.zeros(self.H, dtype=int)
        weights = 3 ** np.arange(self.nd - 1, -1, -1)
        for k in range(self.nd):
            if k != j:
                others += self.device_states(u[k], u_prev[k]) * weights[k]
                others_prev = np.concatenate([[u_prev[k]], u[k, :-1]])
                cost += self.w1 * (u[k] @ self.area_u[k]) \
                    + np.clip(u[k] - others_prev, 0, None) @ self.start_cost[k]
        state = np.where(rows > 0.5, np.where(prev < 0.5, 2, 1), 0)
        combos = others[None, :] + state * weights[j]
        peaks = table[np.arange(self.H)[None, :], combos].max(axis=1)
        return cost + np.array([self.peak_cost(p) for p in peaks])

    @staticmethod
    def device_states(uj: np.ndarray, uj_prev: float) -> np.ndarray:
        """0 off, 1 on, 2 starting, per step."""
        prev = np.concatenate([[uj_prev], uj[:-1]])
        return np.where(uj > 0.5, np.where(prev < 0.5, 2, 1), 0)

    def states_of(self, u: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """(H,) combination index of each step for relay plan ``u``."""
        weights = 3 ** np.arange(self.nd - 1, -1, -1)
        return sum(self.device_states(u[j], u_prev[j]) * weights[j] for j in range(self.nd))

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
        peak = table[np.arange(H), self.states_of(u, u_prev)].max()
        x[self.n_static_cols:] = (levels <= peak + 1e-9) & (peak > z0)
        return x

    def predicted_power(self, u: np.ndarray, u_prev: np.ndarray, free: np.ndarray
                        ) -> np.ndarray:
        """Predicted S at every fine row for relay plan ``u`` (exact, no rounding)."""
        prev = np.concatenate([np.asarray(u_prev, float)[:, None], u[:, :-1]], axis=1)
        s = np.clip(u - prev, 0, None)
        return free + np.einsum("jrh,jh->r", self.Gu, u) + np.einsum("jrh,jh->r", self.Gs, s)


class EEC:
    """The receding-horizon controller: observation in, relay command (and plan) out.

    A :class:`~hil.controllers.base.BenchController` whose ``estimator`` (the Kalman filter of
    :mod:`hil.controllers.bench.kalman`) is fed every meter sample; its ``estimate()`` at the
    decision instant is the ``obs.estimate`` of :meth:`decide` and :meth:`step`.
    """

    def __init__(self, models: BenchModels, problem: BenchProblem, settings: EECSettings,
                 initial: Mapping[str, bool] | None = None, feedback: bool = True,
                 kalman: KalmanSettings | None = None) -> None:
        """``feedback``: use the estimate's disturbance in the predictions (False: the
        models alone, as an open-loop plan would); ``kalman``: the estimator's noise levels."""
        self.estimator = BenchKalman(models, kalman)
        self.problem = problem
        self.settings = settings
        spd = round(settings.step_s / models.dt)
        if abs(spd * models.dt - settings.step_s) > 1e-9:
            raise ValueError(f"decision step {settings.step_s} s is not a whole number of "
                             f"model samples ({models.dt} s)")
        self.prediction = HorizonPrediction(models, problem, settings.hp_steps, spd)
        self.milp = EECMilp(self.prediction, problem, settings)
        self.dwell = DwellClock.start(problem.peripherals, initial)
        self.plan: Plan | None = None
        self._plan_age = 0
        self._first = True
        self.feedback = feedback
        # first call of the cached model products outside the timed path
        self.prediction.free(BenchEstimate.at_rest(models))

    def decide(self, obs: BenchObservation) -> dict[str, bool]:
        """The relay command for ``obs`` (:meth:`step` tells how it was decided)."""
        return self.step(obs).relays

    def step(self, obs: BenchObservation) -> Decision:
        """Decide from ``obs``, whose ``estimate`` is a :class:`BenchEstimate`."""
        if not isinstance(obs.estimate, BenchEstimate):
            raise TypeError(f"the EEC decides from its estimator's BenchEstimate, got "
                            f"{type(obs.estimate).__name__} in obs.estimate")
        names = self.problem.peripherals
        t = obs.t_s
        for name in names:
            self.dwell.update(name, bool(obs.relays.get(name, self.dwell.state[name])), t)
        u_prev = np.array([1.0 if self.dwell.state[n] else 0.0 for n in names])
        if self.plan is not None and self._plan_age < self.settings.hs_steps and \
                np.array_equal(self.plan.u[:, self._plan_age - 1], u_prev):
            command = {n: bool(self.plan.u[j, self._plan_age]) for j, n in enumerate(names)}
            self._plan_age += 1
            return self._commit(Decision(command), t)
        estimate = obs.estimate
        if not self.feedback:
            estimate = BenchEstimate(estimate.sample, estimate.x_machining, estimate.x_devices)
        free = self.prediction.free(estimate)
        fixed = np.array([self._dwell_steps_left(n, t) for n in names])
        q0 = np.array([obs.levels[r.name] for r in self.problem.resources])
        warm = None
        if self.plan is not None:
            shift = self._plan_age
            warm = np.concatenate([self.plan.u[:, shift:],
                                   np.repeat(self.plan.u[:, -1:], shift, axis=1)], axis=1)
        # the very first plan gets a longer budget: there is nothing to start from yet
        budget = self.settings.time_limit_s * (10.0 if self._first else 1.0)
        self._first = False
        result = self.milp.solve(free, u_prev, fixed, q0, t, warm, budget)
        if result.u is None:
            self.plan = None
            command = hysteresis_rule(self.problem, obs.levels, self.dwell, t,
                                      self.settings.step_s)
            reason = f"MILP {result.status}: hysteresis rule for this step"
            return self._commit(Decision(command, None, result, reason,
                                         [("eec.fallback", reason)]), t)
        plan = self._plan(t, result, free, u_prev, q0)
        self.plan, self._plan_age = plan, 1
        command = {n: bool(plan.u[j, 0]) for j, n in enumerate(names)}
        return self._commit(Decision(command, plan, result), t)

    def _dwell_steps_left(self, name: str, t: float) -> int:
        left = self.problem.dwell_s[name] - self.dwell.elapsed(name, t)
        return max(0, math.ceil(left / self.settings.step_s - 1e-6)) if left > 0 else 0

    def _commit(self, decision: Decision, t: float) -> Decision:
        for name, on in decision.relays.items():
            self.dwell.update(name, on, t)
        return decision

    def _plan(self, t: float, result: SolveResult, free: np.ndarray, u_prev: np.ndarray,
              q0: np.ndarray) -> Plan:
        H, step = self.settings.hp_steps, self.settings.step_s
        assert result.u is not None
        power = self.milp.predicted_power(result.u, u_prev, free).reshape(H, -1)
        q = np.empty((len(self.problem.resources), H + 1))
        for j, res in enumerate(self.problem.resources):
            rates = res.alpha * self.milp.consumption(res.consumer, t) \
                + res.eta * step * result.u[j]
            q[j] = q0[j] + np.concatenate([[0.0], np.cumsum(rates)])
        return Plan(t, result.u, q, power.max(axis=1), float(power.max()),
                    float(power.sum() * self.prediction.dt), result.objective, result.status,
                    result.solve_ms, result.rows, result.gap, result.nodes, result.bound)
