"""The EEC's MILP written with cvxpy: the reference for tests and the naive baseline.

Same problem as :class:`hil.controllers.bench.eec_milp.EECMilp` (same predictions, J1
coefficients, weights, level bounds: :class:`~hil.controllers.bench.eec_costs.HorizonCosts`),
written the direct way: the total power on every fine-grid sample, ``z >= S(r)`` for all of
them, ``e >= z - limit``. Two uses:

* :class:`CvxpyEEC`: built once with ``cp.Parameter`` for everything that changes between
  solves (the free response, the relay state, the running dwell, the level bounds); the tests
  check the fast HiGHS model against it.
* :func:`solve_naive`: the "straightforward" formulation rebuilt for every decision (boolean
  relays only, the weak pairwise dwell rows, continuous level bounds), as a user of cvxpy would
  first write it: the baseline of ``benchmarks/eec.py``.

Both solve with HiGHS through cvxpy.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cvxpy as cp
import numpy as np

from hil.controllers.bench.eec_costs import HorizonCosts


@dataclass
class ReferenceResult:
    status: str
    u: np.ndarray | None
    objective: float   # J without the constant machining area (comparable to EECMilp's)
    peak_va: float
    solve_ms: float


class CvxpyEEC:
    """The MILP as a parametrised cvxpy problem (built once, solved many times)."""

    def __init__(self, horizon: HorizonCosts, time_limit_s: float = 60.0) -> None:
        self.horizon = horizon
        H, nd = horizon.H, horizon.nd
        R = horizon.p.rows
        self.free = cp.Parameter(R)
        self.u_prev = cp.Parameter(nd)
        self.u_lo = cp.Parameter((nd, H))
        self.u_hi = cp.Parameter((nd, H))
        self.c_lo = cp.Parameter((nd, H))
        self.c_hi = cp.Parameter((nd, H))
        u = cp.Variable((nd, H), boolean=True)
        s = cp.Variable((nd, H))
        d = cp.Variable((nd, H))
        z = cp.Variable()
        cons = [s >= 0, s <= 1, d >= 0, d <= 1, u >= self.u_lo, u <= self.u_hi]
        power = self.free
        cost = 0
        for j in range(nd):
            prev = cp.hstack([cp.reshape(self.u_prev[j], (1,), order="C"), u[j, :-1]])
            cons.append(u[j] - prev == s[j] - d[j])
            L = horizon.dwell_steps[j]
            if L > 1:
                for i in range(H):
                    lo = max(0, i - L + 1)
                    cons.append(cp.sum(s[j, lo:i + 1]) <= u[j, i])
                    cons.append(cp.sum(d[j, lo:i + 1]) <= 1 - u[j, i])
            c = cp.cumsum(u[j])
            cons += [c >= self.c_lo[j], c <= self.c_hi[j]]
            power = power + horizon.Gu[j] @ u[j] + horizon.Gs[j] @ s[j]
            cost = cost + horizon.w1 * (horizon.area_u[j] @ u[j]) + horizon.start_cost[j] @ s[j]
        cons.append(z >= power)
        cost = cost + horizon.w2 * z
        if horizon.settings.limit_va is not None:
            e = cp.Variable(nonneg=True)
            cons.append(e >= z - float(horizon.settings.limit_va))
            cost = cost + horizon.w_limit * e
        self.u, self.z = u, z
        self.problem = cp.Problem(cp.Minimize(cost), cons)
        self.time_limit_s = time_limit_s

    def solve(self, free: np.ndarray, u_prev: np.ndarray, fixed_steps: np.ndarray,
              q0: np.ndarray, t_s: float) -> ReferenceResult:
        horizon, H = self.horizon, self.horizon.H
        qlo, qhi = horizon.level_bounds(q0, t_s)
        self.free.value = np.asarray(free, float)
        self.u_prev.value = np.asarray(u_prev, float)
        lo, hi = np.zeros((horizon.nd, H)), np.ones((horizon.nd, H))
        for j in range(horizon.nd):
            k = int(min(fixed_steps[j], H))
            lo[j, :k] = hi[j, :k] = u_prev[j]
        self.u_lo.value, self.u_hi.value = lo, hi
        self.c_lo.value, self.c_hi.value = np.maximum(qlo, 0.0), qhi
        t0 = time.perf_counter()
        try:
            self.problem.solve(solver=cp.HIGHS, time_limit=self.time_limit_s)
        except cp.error.SolverError as exc:
            return ReferenceResult(f"error: {exc}", None, float("nan"), float("nan"),
                                   (time.perf_counter() - t0) * 1e3)
        ms = (time.perf_counter() - t0) * 1e3
        u, z = self.u.value, self.z.value
        if u is None or z is None:
            return ReferenceResult(self.problem.status, None, float("nan"), float("nan"), ms)
        return ReferenceResult(self.problem.status, np.rint(u).astype(int),
                               float(self.problem.value), float(z), ms)


def solve_naive(horizon: HorizonCosts, free: np.ndarray, u_prev: np.ndarray,
                fixed_steps: np.ndarray, q0: np.ndarray, t_s: float, time_limit_s: float = 60.0
                ) -> ReferenceResult:
    """Build and solve the straightforward formulation (every call from scratch)."""
    t0 = time.perf_counter()
    H, nd = horizon.H, horizon.nd
    u = cp.Variable((nd, H), boolean=True)
    z = cp.Variable()
    cons = []
    power = np.asarray(free, float)
    cost = 0
    for j, res in enumerate(horizon.problem.resources):
        prev = cp.hstack([np.array([float(u_prev[j])]), u[j, :-1]])
        s = cp.Variable(H, nonneg=True)
        cons.append(s >= u[j] - prev)
        k = int(min(fixed_steps[j], H))
        if k:
            cons.append(u[j, :k] == float(u_prev[j]))
        L = horizon.dwell_steps[j]
        for i in range(H):  # a switch at i holds for L steps (pairwise rows)
            for m in range(i + 1, min(H, i + L)):
                cons.append(u[j, i] - prev[i] <= u[j, m])
                cons.append(prev[i] - u[j, i] <= 1 - u[j, m])
        used = horizon.consumption(res.consumer, t_s)
        q = q0[j] + res.alpha * np.cumsum(used) \
            + res.eta * horizon.settings.step_s * cp.cumsum(u[j])
        cons += [q >= res.q_min, q <= res.q_max]
        if horizon.settings.terminal == "hold":
            cons.append(q[H - 1] >= min(res.q0, res.q_max - res.eta * horizon.settings.step_s))
        power = power + horizon.Gu[j] @ u[j] + horizon.Gs[j] @ s
        cost = cost + horizon.w1 * (horizon.area_u[j] @ u[j]) + horizon.start_cost[j] @ s
    cons.append(z >= power)
    cost = cost + horizon.w2 * z
    if horizon.settings.limit_va is not None:
        cost = cost + horizon.w_limit * cp.pos(z - float(horizon.settings.limit_va))
    problem = cp.Problem(cp.Minimize(cost), cons)
    try:
        problem.solve(solver=cp.HIGHS, time_limit=time_limit_s)
    except cp.error.SolverError as exc:
        return ReferenceResult(f"error: {exc}", None, float("nan"), float("nan"),
                               (time.perf_counter() - t0) * 1e3)
    ms = (time.perf_counter() - t0) * 1e3
    u_value, z_value = u.value, z.value
    if u_value is None or z_value is None:
        return ReferenceResult(problem.status, None, float("nan"), float("nan"), ms)
    return ReferenceResult(problem.status, np.rint(u_value).astype(int), float(problem.value),
                           float(z_value), ms)
