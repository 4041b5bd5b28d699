"""One horizon's plan of the EEC by the configured solver: the schedule DP or the MILP.

:class:`HorizonSolver` bounds the on-steps by the levels, tabulates the step peaks, and hands
the horizon to the schedule DP (``solver = "dp"``, :mod:`hil.controllers.bench.eec_dp`, the
default) or to the MILP (``solver = "milp"``, :mod:`hil.controllers.bench.eec_milp`).

Solve time: the LP relaxation stays weak when the plan must trade peak against energy (it
spreads fractional "thin" runs over the horizon), so HiGHS proves some instants only after
0.3-0.7 s of root cuts and branching. The DP finds the same optimum exactly by a pruned dynamic
program over the relay schedules (bounds from per-peripheral cost-to-go under a few peak caps,
dominance, the previous plan and a beam search as incumbents), in a few ms at H_p = T; the
MILP stays as the general formulation and the reference. ``time_limit_s`` is a safety net:
at the limit the best plan found is used (status ``time_limit``, its gap recorded). ``nodes``
of a DP solve counts the partial plans its searches kept.
"""

from __future__ import annotations

import math
import time

import numpy as np

from hil.controllers.bench.eec_costs import HorizonCosts
from hil.controllers.bench.eec_dp import DeviceGraph, ScheduleDP
from hil.controllers.bench.eec_milp import EECMilp
from hil.controllers.bench.eec_settings import EECSettings, SolveResult
from hil.controllers.bench.prediction import HorizonPrediction
from hil.controllers.bench.problem import BenchProblem


class HorizonSolver:
    """The plan of one horizon: its costs (:class:`HorizonCosts`) built once, the MILP and,
    with ``solver = "dp"``, the schedule DP over them."""

    def __init__(self, prediction: HorizonPrediction, problem: BenchProblem,
                 settings: EECSettings) -> None:
        self.horizon = HorizonCosts(prediction, problem, settings)
        self.milp = EECMilp(self.horizon)
        self.dp = ScheduleDP([DeviceGraph(self.horizon.H, L, L)
                              for L in self.horizon.dwell_steps]) \
            if settings.solver == "dp" else None

    def solve(self, free: np.ndarray, u_prev: np.ndarray, fixed_steps: np.ndarray,
              q0: np.ndarray, t_s: float, warm_u: np.ndarray | None = None,
              budget_s: float | None = None) -> SolveResult:
        """Solve for the plan. ``fixed_steps[j]``: steps u_j must keep ``u_prev[j]`` (the dwell
        still running); ``q0``: levels now; ``warm_u`` (devices x H): a candidate plan (made
        feasible by :func:`~hil.controllers.bench.eec_repair.repair` if it can be);
        ``budget_s``: solver time limit (default the settings' ``time_limit_s``)."""
        t0 = time.perf_counter()
        horizon = self.horizon
        qlo, qhi = horizon.level_bounds(q0, t_s)
        c_lo, c_hi = np.maximum(qlo, 0.0), np.minimum(qhi, np.arange(horizon.H) + 1.0)
        if np.any(c_lo > c_hi):
            return SolveResult("infeasible", None, math.nan, math.nan,
                               (time.perf_counter() - t0) * 1e3, 0, False)
        table = horizon.peak_table(free)
        budget = horizon.settings.time_limit_s if budget_s is None else budget_s
        if self.dp is not None:
            return self._solve_dp(t0, table, u_prev, fixed_steps, c_lo, c_hi, warm_u, budget)
        return self.milp.solve(t0, table, u_prev, fixed_steps, c_lo, c_hi, warm_u, budget)

    def _solve_dp(self, t0: float, table: np.ndarray, u_prev: np.ndarray,
                  fixed_steps: np.ndarray, c_lo: np.ndarray, c_hi: np.ndarray,
                  warm_u: np.ndarray | None, budget: float) -> SolveResult:
        """The same optimum by the schedule DP (:mod:`~hil.controllers.bench.eec_dp`);
        the previous plan (made feasible) is an incumbent, ``budget`` a safety net (status
        ``time_limit``)."""
        assert self.dp is not None
        horizon = self.horizon
        z0 = float(table[:, 0].max())
        found = self.dp.solve(u_prev, fixed_steps, horizon.class_costs, c_lo, c_hi, table,
                              horizon.peak_costs, warm_u, t0 + budget)
        solve_ms = (time.perf_counter() - t0) * 1e3
        proven = found.bound >= found.objective
        if found.u is None:
            return SolveResult("infeasible", None, math.nan, math.nan, solve_ms, 0, False)
        u = found.u.astype(int)
        peak = max(z0, float(table[np.arange(horizon.H), horizon.states_of(u, u_prev)].max()))
        gap = 0.0 if proven else (found.objective - found.bound) / max(abs(found.objective),
                                                                       1e-12)
        return SolveResult("optimal" if proven else "time_limit", u, found.objective, peak,
                           solve_ms, 0, warm_u is not None, gap=gap, nodes=found.expanded,
                           bound=found.bound)
