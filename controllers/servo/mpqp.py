"""Multiparametric quadratic programming: the explicit solution of a parametric QP over a box.

Problem (the condensed MPC (9)/(13) of the servo paper, with an optional constant term f)::

    z*(p) = argmin ½ z'Hz + (F'p + f)'z   s.t.   G z <= W + X p,      lower <= p <= upper

with H positive definite. The optimiser is piecewise affine in p (Bemporad et al. 2002):
for each optimal active set A the KKT conditions give z*(p) = K p + k and multipliers
λ(p) = L p + l, valid on the *critical region* {p in box : G_I z*(p) <= W_I + X_I p,
λ(p) >= 0} (I = inactive rows). :func:`solve_mpqp` enumerates the active sets with the
combinatorial method and its feasibility pruning (Gupta, Bhartiya, Nataraj 2011): active sets
are visited by increasing size; a set whose constraints cannot all hold with equality at any
feasible (z, p) is infeasible and so are all its supersets, which are never visited; a set
whose rows are linearly dependent (LICQ fails) is skipped with its supersets. Every
full-dimensional critical region (Chebyshev ball radius > ``radius_tol`` in box-normalised
coordinates) is kept, with its redundant half-spaces removed by linear programs (highspy);
thinner ones are counted as ``slivers`` in the stats (a region-free gap, see ``covers_box``).

All geometry is done in box-normalised coordinates t in [-1, 1]^n (p = centre + half_width *
t): the parameters of an MPC span many orders of magnitude (state increments of 1e-5 next to
currents of 1e3), and tolerances mean the same thing in every direction there. The regions
are returned in the caller's coordinates p, each half-space row scaled to unit norm in t.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import highspy
import numpy as np
import scipy.linalg as sla

from hil.controllers.errors import ControllerSetupError, SolverError
from hil.controllers.highs import silent_highs

_INF = highspy.kHighsInf


class LinearProgram:
    """A reusable highspy instance for the small dense LPs of the mpQP and the search tree."""

    def __init__(self) -> None:
        self._highs = silent_highs()
        self.count = 0

    def solve(self, c: np.ndarray, A: np.ndarray, b: np.ndarray,
              lower: np.ndarray, upper: np.ndarray,
              A_eq: np.ndarray | None = None, b_eq: np.ndarray | None = None,
              ) -> np.ndarray | None:
        """argmin c'x s.t. A x <= b, A_eq x = b_eq, lower <= x <= upper; None if infeasible."""
        n = c.size
        rows = [np.asarray(A, float).reshape(-1, n)]
        row_lo = [np.full(rows[0].shape[0], -_INF)]
        row_hi = [np.asarray(b, float)]
        if A_eq is not None and A_eq.shape[0]:
            rows.append(np.asarray(A_eq, float))
            row_lo.append(np.asarray(b_eq, float))
            row_hi.append(np.asarray(b_eq, float))
        M = np.vstack(rows)
        lp = highspy.HighsLp()
        lp.num_col_ = n
        lp.num_row_ = M.shape[0]
        lp.col_cost_ = np.asarray(c, float)
        lp.col_lower_ = np.asarray(lower, float)
        lp.col_upper_ = np.asarray(upper, float)
        lp.row_lower_ = np.concatenate(row_lo)
        lp.row_upper_ = np.concatenate(row_hi)
        lp.a_matrix_.format_ = highspy.MatrixFormat.kRowwise
        lp.a_matrix_.start_ = np.arange(0, M.size + 1, n, dtype=np.int32)
        lp.a_matrix_.index_ = np.tile(np.arange(n, dtype=np.int32), M.shape[0])
        lp.a_matrix_.value_ = M.ravel()
        h = self._highs
        h.clearModel()
        h.passModel(lp)
        h.run()
        self.count += 1
        if h.getModelStatus() != highspy.HighsModelStatus.kOptimal:
            return None
        return np.asarray(h.getSolution().col_value, dtype=float)

    def minima(self, A: np.ndarray, b: np.ndarray, directions: np.ndarray) -> np.ndarray | None:
        """min c't over {A t <= b} ∩ [-1, 1]^n for each row c of ``directions`` (one model,
        warm-started re-solves); None if the set is empty."""
        n = A.shape[1]
        if self.solve(np.zeros(n), A, b, -np.ones(n), np.ones(n)) is None:
            return None
        h = self._highs
        index = np.arange(n, dtype=np.int32)
        values = np.empty(directions.shape[0])
        for i, c in enumerate(directions):
            h.changeColsCost(n, index, np.asarray(c, float))
            h.run()
            self.count += 1
            if h.getModelStatus() != highspy.HighsModelStatus.kOptimal:
                raise SolverError(f"LP over a non-empty bounded set ended with "
                               f"{h.modelStatusToString(h.getModelStatus())}")
            values[i] = h.getInfo().objective_function_value
        return values

    def chebyshev(self, A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
        """Centre and radius of the largest ball in {t : A t <= b} ∩ [-1, 1]^n (radius <= 1);
        radius -1 when the set is empty."""
        n = A.shape[1]
        norms = np.linalg.norm(A, axis=1)
        c = np.zeros(n + 1)
        c[-1] = -1.0
        lower = np.concatenate([np.full(n, -1.0), [0.0]])
        upper = np.concatenate([np.full(n, 1.0), [1.0]])
        # The box itself: t_i + r <= 1 and -t_i + r <= 1.
        box = np.hstack([np.vstack([np.eye(n), -np.eye(n)]), np.ones((2 * n, 1))])
        sol = self.solve(c, np.vstack([np.hstack([A, norms[:, None]]), box]),
                         np.concatenate([b, np.ones(2 * n)]), lower, upper)
        if sol is None:
            return np.zeros(n), -1.0
        return sol[:n], float(sol[n])


@dataclass(frozen=True)
class MpQP:
    """min ½ z'Hz + (F'p + f)'z s.t. G z <= W + X p, over the box lower <= p <= upper.

    Shapes: H (n_z, n_z), F (n_p, n_z), f (n_z,), G (n_c, n_z), W (n_c,), X (n_c, n_p).
    """

    H: np.ndarray
    F: np.ndarray
    G: np.ndarray
    W: np.ndarray
    X: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    f: np.ndarray | None = None

    def __post_init__(self) -> None:
        n_z, n_p, n_c = self.H.shape[0], self.F.shape[0], self.G.shape[0]
        shapes = {"H": (n_z, n_z), "F": (n_p, n_z), "G": (n_c, n_z), "W": (n_c,),
                  "X": (n_c, n_p), "lower": (n_p,), "upper": (n_p,)}
        for name, shape in shapes.items():
            if np.shape(getattr(self, name)) != shape:
                raise ControllerSetupError(
                    f"mpqp: {name} has shape {np.shape(getattr(self, name))}, "
           f"expected {shape}")
        if not np.all(np.isfinite(self.lower)) or not np.all(np.isfinite(self.upper)):
            raise ControllerSetupError("mpqp: the parameter box must be finite")
        if not np.all(np.asarray(self.upper) > np.asarray(self.lower)):
            raise ControllerSetupError("mpqp: every box interval must have upper > lower")

    @property
    def n_params(self) -> int:
        return self.F.shape[0]

    @property
    def n_vars(self) -> int:
        return self.H.shape[0]

    @property
    def centre(self) -> np.ndarray:
        return 0.5 * (np.asarray(self.upper, float) + np.asarray(self.lower, float))

    @property
    def half_width(self) -> np.ndarray:
        return 0.5 * (np.asarray(self.upper, float) - np.asarray(self.lower, float))

    def normalised(self) -> MpQP:
        """The same problem in t = (p - centre) / half_width, over [-1, 1]^n."""
        c, d = self.centre, self.half_width
        f = np.zeros(self.n_vars) if self.f is None else np.asarray(self.f, float)
        return MpQP(H=self.H, F=d[:, None] * self.F, f=f + self.F.T @ c, G=self.G,
                    W=self.W + self.X @ c, X=self.X * d[None, :],
                    lower=-np.ones(self.n_params), upper=np.ones(self.n_params))


@dataclass(frozen=True)
class CriticalRegion:
    """A critical region {p : A p <= b} with its optimiser z*(p) = K p + k.

    ``active``: the optimal active set (row indices of G). ``boundary`` flags the rows that
    are facets of the parameter box. ``centre``/``radius``: Chebyshev ball in normalised
    coordinates (radius relative to the box half-width).
    """

    active: tuple[int, ...]
    A: np.ndarray
    b: np.ndarray
    boundary: np.ndarray
    K: np.ndarray
    k: np.ndarray
    centre: np.ndarray
    radius: float

    def contains(self, p: np.ndarray, tol: float = 1e-9) -> bool:
        return bool(np.all(self.A @ p <= self.b + tol))

    def optimiser(self, p: np.ndarray) -> np.ndarray:
        return self.K @ p + self.k


@dataclass
class MpqpSolution:
    """The explicit solution: critical regions over the box, and how it was found."""

    problem: MpQP
    regions: list[CriticalRegion]
    build_s: float
    stats: dict[str, int] = field(default_factory=dict)

    @property
    def covers_box(self) -> bool:
        """Do the regions provably cover the box? Yes when z = 0 is feasible for every p in
        the box (so is the QP, and its full-dimensional critical regions cover the box up to
        lower-dimensional sets) and no region was dropped as thinner than ``radius_tol``."""
        qp = self.problem
        worst = qp.W + qp.X @ qp.centre - np.abs(qp.X) @ qp.half_width
        return bool(np.all(worst >= 0) and self.stats.get("slivers", 0) == 0)

    def optimiser(self, p: np.ndarray, tol: float = 1e-9) -> np.ndarray | None:
        """z*(p) from the first region containing ``p``, None outside every region."""
        for region in self.regions:
            if region.contains(p, tol):
                return region.optimiser(p)
        return None

    def law_labels(self, rows: slice | None = None, rtol: float = 1e-7) -> np.ndarray:
        """Per region, the index of its distinct law (equal K and k, on ``rows`` of z only:
        ``slice(0, 1)`` compares the first move, what a receding-horizon controller applies).
        Tolerance: ``rtol`` times the largest gain in normalised coordinates."""
        rows = rows or slice(None)
        d = self.problem.half_width
        gains = [np.hstack([r.K[rows] * d[None, :], (r.K[rows] @ self.problem.centre
                                                    + r.k[rows])[:, None]])
                 for r in self.regions]
        scale = max((float(np.abs(g).max()) for g in gains), default=1.0) or 1.0
        labels = np.full(len(gains), -1)
        representatives: list[np.ndarray] = []
        for i, g in enumerate(gains):
            for j, rep in enumerate(representatives):
                if np.abs(g - rep).max() <= rtol * scale:
                    labels[i] = j
                    break
            else:
                labels[i] = len(representatives)
                representatives.append(g)
        return labels


class _Solver:
    """Enumeration state of one :func:`solve_mpqp` call, in normalised coordinates."""

    def __init__(self, qp: MpQP, radius_tol: float, lp: LinearProgram) -> None:
        self.qp = qp
        self.lp = lp
        self.radius_tol = radius_tol
        chol = sla.cho_factor(qp.H)
        self.Hinv = sla.cho_solve(chol, np.eye(qp.n_vars))
        self.Z = -self.Hinv @ qp.F.T  # unconstrained optimiser Z t + z0
        self.z0 = -self.Hinv @ qp.f
        self.stats = {"candidates": 0, "infeasible": 0, "degenerate": 0, "empty": 0,
                      "slivers": 0}

    def feasible(self, active: tuple[int, ...]) -> bool:
        """Can the rows of ``active`` hold with equality at some feasible (z, t)?"""
        qp, nz, n = self.qp, self.qp.n_vars, self.qp.n_params
        act = list(active)
        A = np.hstack([qp.G, -qp.X])
        sol = self.lp.solve(np.zeros(nz + n), A, qp.W,
                            np.concatenate([np.full(nz, -_INF), -np.ones(n)]),
                            np.concatenate([np.full(nz, _INF), np.ones(n)]),
                            A_eq=A[act], b_eq=qp.W[act])
        return sol is not None

    def region(self, active: tuple[int, ...]) -> CriticalRegion | None:
        """The critical region of ``active`` (None when not full-dimensional)."""
        qp = self.qp
        act = list(active)
        inactive = [i for i in range(qp.G.shape[0]) if i not in active]
        if act:
            GA = qp.G[act]
            M = GA @ self.Hinv @ GA.T
            L = np.linalg.solve(M, GA @ self.Z - qp.X[act])
            l_ = np.linalg.solve(M, GA @ self.z0 - qp.W[act])
            K = self.Z - self.Hinv @ GA.T @ L
            k = self.z0 - self.Hinv @ GA.T @ l_
        else:
            L = np.zeros((0, qp.n_params))
            l_ = np.zeros(0)
            K, k = self.Z, self.z0
        GI = qp.G[inactive]
        A = np.vstack([GI @ K - qp.X[inactive], -L])  # primal feasibility, λ >= 0
        b = np.concatenate([qp.W[inactive] - GI @ k, l_])
        rows = _normalise_rows(A, b)
        if rows is None:
            return None
        A, b = rows
        centre, radius = self.lp.chebyshev(A, b)
        if radius <= self.radius_tol:
            if radius > 0:
                self.stats["slivers"] += 1
            return None
        A, b, boundary = self.irredundant(A, b)
        return CriticalRegion(active=active, A=A, b=b, boundary=boundary, K=K, k=k,
                              centre=centre, radius=radius)

    def irredundant(self, A: np.ndarray, b: np.ndarray,
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Remove redundant rows of {A t <= b} ∩ box; the kept box facets are appended."""
        n = A.shape[1]
        box_A = np.vstack([np.eye(n), -np.eye(n)])
        A_all = np.vstack([A, box_A])
        b_all = np.concatenate([b, np.ones(2 * n)])
        is_box = np.concatenate([np.zeros(A.shape[0], bool), np.ones(2 * n, bool)])
        keep = np.ones(A_all.shape[0], bool)
        # Rows implied by the box alone: max over the box of a't is sum |a_i|.
        keep[: A.shape[0]] = np.abs(A).sum(axis=1) > b + 1e-12
        keep = _drop_duplicates(A_all, b_all, keep)
        for i in np.flatnonzero(keep):
            keep[i] = False
            others = np.flatnonzero(keep)
            # max a_i't subject to the other kept rows (and a_i't <= b_i + 1, so bounded).
            sol = self.lp.solve(-A_all[i], np.vstack([A_all[others], A_all[i]]),
                                np.concatenate([b_all[others], [b_all[i] + 1.0]]),
                                np.full(n, -_INF), np.full(n, _INF))
            keep[i] = sol is None or float(A_all[i] @ sol) > b_all[i] + 1e-9
        return A_all[keep], b_all[keep], is_box[keep]


def _normalise_rows(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Rows scaled to unit norm; rows 0't <= b dropped (None if such a row is violated)."""
    norms = np.linalg.norm(A, axis=1)
    zero = norms <= 1e-12 * max(1.0, float(norms.max(initial=0.0)))
    if np.any(b[zero] < -1e-9):
        return None
    keep = ~zero
    return A[keep] / norms[keep, None], b[keep] / norms[keep]


def _drop_duplicates(A: np.ndarray, b: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Of rows with the same unit normal, keep only the tightest (the later one on a tie)."""
    keep = keep.copy()
    idx = np.flatnonzero(keep)
    for a_pos, i in enumerate(idx):
        if not keep[i]:
            continue
        for j in idx[a_pos + 1:]:
            if keep[j] and np.abs(A[i] - A[j]).max() <= 1e-10:
                if b[j] <= b[i]:  # on a tie the later row (a box facet) stays
                    keep[i] = False
                    break
                keep[j] = False
    return keep


def solve_mpqp(problem: MpQP, radius_tol: float = 1e-6,
               max_active: int | None = None) -> MpqpSolution:
    """Every full-dimensional critical region of ``problem`` over its box (see module doc).

    ``max_active`` caps the active-set size (default: the number of decision variables,
    the most linearly independent rows there can be).
    """
    start = time.perf_counter()
    qp = problem.normalised()
    lp = LinearProgram()
    solver = _Solver(qp, radius_tol, lp)
    n_c = qp.G.shape[0]
    cap = qp.n_vars if max_active is None else min(max_active, qp.n_vars)
    regions_t: list[CriticalRegion] = []
    level: list[tuple[int, ...]] = [()]
    feasible_sets: set[tuple[int, ...]] = {()}
    size = 0
    while level:
        next_level: list[tuple[int, ...]] = []
        for active in level:
            solver.stats["candidates"] += 1
            region = solver.region(active)
            if region is None:
                solver.stats["empty"] += 1
            else:
                regions_t.append(region)
            if size == cap:
                continue
            for j in range(active[-1] + 1 if active else 0, n_c):
                candidate = (*active, j)
                # Every subset one smaller must be feasible (else a superset of an infeasible
                # set) -- the combinatorial pruning.
                if any(sub not in feasible_sets
                       for sub in itertools.combinations(candidate, size)):
                    continue
                if np.linalg.matrix_rank(qp.G[list(candidate)]) < len(candidate):
                    solver.stats["degenerate"] += 1
                    continue
                if not solver.feasible(candidate):
                    solver.stats["infeasible"] += 1
                    continue
                feasible_sets.add(candidate)
                next_level.append(candidate)
        level = next_level
        size += 1
    regions = [_to_user_coordinates(r, problem) for r in regions_t]
    stats = dict(solver.stats, lps=lp.count, regions=len(regions))
    return MpqpSolution(problem=problem, regions=regions,
                        build_s=time.perf_counter() - start, stats=stats)


def _to_user_coordinates(region: CriticalRegion, problem: MpQP) -> CriticalRegion:
    """Map a region found in t = (p - c)/d back to p (rows keep their unit norm in t)."""
    c, d = problem.centre, problem.half_width
    A = region.A / d[None, :]
    K = region.K / d[None, :]
    return CriticalRegion(active=region.active, A=A, b=region.b + A @ c,
                          boundary=region.boundary, K=K, k=region.k - K @ c,
                          centre=c + d * region.centre, radius=region.radius)
