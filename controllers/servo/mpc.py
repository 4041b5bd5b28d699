"""Trajectory-tracking MPC of the servo paper (section II) with a trajectory horizon H_t.

Model: the velocity form (eq. 2-5) of the plant, state x = [Δx_p; y], input Δu; deciding Δu
gives the controller integral action. Prediction over H_p steps (eq. 8): Y = Ψ x + Θ ΔU with
Δu(i) = 0 for i >= H_u. The cost (7) weighs the error to the reference r(1..H_t-2) and, from
i = H_t-1 on, to the extended reference trajectory (ERT): zero-order hold r̂(i) = r(H_t) or
first-order hold r̂(i) = r(H_t-1) + (i-H_t+1)(r(H_t)-r(H_t-1)) (needs H_t >= 2). Condensed,
the problem is the QP (9) in the H_u moves with the parameter vector
θ = [x; u(k-1); r(1|k) .. r(H_t|k)] and the constraints (10)-(13) on u, Δu and y:

    min ½ ΔU' H ΔU + θ' F ΔU   s.t.   G ΔU <= W + X θ.

Online solver (:class:`DaqpSolver`): H is constant, so -H⁻¹F' is precomputed; the
unconstrained optimum K θ is accepted when it satisfies every constraint (then it is the
constrained optimum too), otherwise the dense active-set solver daqp, set up once with H and
G, solves the QP warm-started from the previous active set. :class:`CvxpyReferenceSolver` is an
independent formulation (states rolled forward step by step, the ERT written elementwise from
the paper) that the tests and the benchmark compare against.

Modulo 360: the axis reports its position in [0, 360). :class:`TrajectoryMpc` unwraps the
measured position and the reference into continuous angles (both may wrap; less than 180 deg
per tick), anchoring the reference within ±180 deg of the first measurement, so a reference
crossing 360 -> 0 is just a continuing motion. Output constraints (y_min, y_max) apply in that
continuous frame, which starts at the first measured position.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, ClassVar, Protocol

import daqp
import numpy as np
import scipy.linalg as sla

from hil.controllers.base import TunableParam
from hil.controllers.errors import ControllerSetupError, SolverError
from hil.controllers.servo.kalman import KalmanTuning, SteadyStateKalman
from hil.controllers.servo.model import StateSpaceModel, published_axis_model
from hil.controllers.servo.references import AngleUnwrapper, Reference

FEASIBILITY_TOL = 1e-7  # constraint slack accepted on the unconstrained fast path [mA or deg]


def velocity_form(model: StateSpaceModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A, B, C of eq. (5): state [Δx_p; y], input Δu, output y."""
    Ap, Bp, Cp = model.A, model.B, model.C
    n, m = Ap.shape[0], Cp.shape[0]
    A = np.block([[Ap, np.zeros((n, m))], [Cp @ Ap, np.eye(m)]])
    B = np.vstack([Bp, Cp @ Bp])
    C = np.hstack([np.zeros((m, n)), np.eye(m)])
    return A, B, C


def prediction_matrices(A: np.ndarray, B: np.ndarray, C: np.ndarray,
                        hp: int, hu: int) -> tuple[np.ndarray, np.ndarray]:
    """Ψ (H_p x n_x) and Θ (H_p x H_u) of eq. (8), single input and output."""
    rows, markov = [], []
    power = np.eye(A.shape[0])
    for _ in range(hp):
        markov.append((C @ power @ B).item())  # C A^(i-1) B
        power = A @ power
        rows.append(C @ power)  # C A^i
    Psi = np.vstack(rows)
    Theta = np.zeros((hp, hu))
    for i in range(hp):
        for j in range(min(i + 1, hu)):
            Theta[i, j] = markov[i - j]
    return Psi, Theta


def reference_expansion(ht: int, hp: int, ert: str) -> np.ndarray:
    """The H_p x H_t matrix mapping r(1..H_t|k) to the reference used at i = 1..H_p in (7).

    Rows i <= H_t-2 pick r(i); from i = H_t-1 on, the ERT: ZOH holds r(H_t) (and uses
    r(H_t-1) at i = H_t-1), FOH extrapolates the line through r(H_t-1), r(H_t) (the Λ of the
    paper). H_t = 1 with ZOH is set-point tracking.
    """
    T = np.zeros((hp, ht))
    for i in range(1, hp + 1):
        if i <= ht - 2 or (ert == "zoh" and i <= ht):
            T[i - 1, i - 1] = 1.0
        elif ert == "zoh":
            T[i - 1, ht - 1] = 1.0
        else:
            T[i - 1, ht - 2] = ht - i
            T[i - 1, ht - 1] = i - ht + 1
    return T


def _weights(value: float | Sequence[float], count: int, name: str, strict: bool) -> np.ndarray:
    w = np.asarray(value, dtype=float)
    if w.ndim == 0:
        w = np.full(count, float(w))
    if w.shape != (count,):
        raise ControllerSetupError(
            f"mpc.{name}: expected a number or {count} numbers, got {w.size}")
    if np.any(~np.isfinite(w)) or np.any(w <= 0 if strict else w < 0):
        raise ControllerSetupError(
            f"mpc.{name}: weights must be finite and {'> 0' if strict else '>= 0'}")
    return w


@dataclass(frozen=True)
class MpcConfig:
    """Horizons, ERT, weights Q(i) (i = 1..H_p) and R(i) (i = 0..H_u-1), constraints (10)-(12).

    A bound of None is absent. Defaults are the paper's simulation section: FOH, H_t = H_u = 8,
    H_p = 50, Q = 1e6, R = 1, |u| <= 1000 mA.
    """

    ht: int = 8
    hu: int = 8
    hp: int = 50
    ert: str = "foh"
    q: float | Sequence[float] = 1e6
    r: float | Sequence[float] = 1.0
    u_min: float = -1000.0
    u_max: float = 1000.0
    du_min: float | None = None
    du_max: float | None = None
    y_min: float | None = None
    y_max: float | None = None

    def __post_init__(self) -> None:
        if self.ert not in ("foh", "zoh"):
            raise ControllerSetupError(f"mpc.ert must be 'foh' or 'zoh', got {self.ert!r}")
        for name in ("ht", "hu", "hp"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ControllerSetupError(f"mpc.{name} must be a positive integer, got {value!r}")
        if self.ht > self.hp or self.hu > self.hp:
            raise ControllerSetupError(f"mpc: H_t ({self.ht}) and H_u ({self.hu}) must not exceed "
                              f"H_p ({self.hp})")
        if self.ert == "foh" and self.ht < 2:
            raise ControllerSetupError(
                "mpc: a first-order-hold ERT needs H_t >= 2 (use zoh for H_t = 1)")
        _weights(self.q, self.hp, "q", strict=False)
        _weights(self.r, self.hu, "r", strict=True)
        if not self.u_min < 0 < self.u_max:
            raise ControllerSetupError(
                f"mpc: need u_min < 0 < u_max, got {self.u_min}, {self.u_max}")
        if (self.du_min is not None and not self.du_min < 0) or (
                self.du_max is not None and not self.du_max > 0):
            raise ControllerSetupError(
                "mpc: need du_min < 0 < du_max (holding the current is feasible)")
        if self.y_min is not None and self.y_max is not None and not self.y_min < self.y_max:
            raise ControllerSetupError(f"mpc: need y_min < y_max, got {self.y_min}, {self.y_max}")


@dataclass(frozen=True)
class CondensedQP:
    """The parametric QP (9)/(13): min ½ΔU'HΔU + θ'FΔU s.t. GΔU <= W + Xθ.

    θ = [x (n_x); u(k-1); r(1|k) .. r(H_t|k)]. Ψ, Θ and the reference expansion are kept for
    predictions; ``output_rows`` is how many of G's last rows are output (y) constraints.
    """

    H: np.ndarray
    F: np.ndarray
    G: np.ndarray
    W: np.ndarray
    X: np.ndarray
    Psi: np.ndarray
    Theta: np.ndarray
    ref_expansion: np.ndarray
    n_x: int
    output_rows: int

    @property
    def n_theta(self) -> int:
        return self.F.shape[0]

    def theta(self, x: np.ndarray, u_prev: float, r: np.ndarray) -> np.ndarray:
        return np.concatenate([np.asarray(x, float), [float(u_prev)], np.asarray(r, float)])


def condense(config: MpcConfig, model: StateSpaceModel | None = None) -> CondensedQP:
    """Build H, F, G, W, X of (9) and (13) for ``model`` (default: the published axis)."""
    model = model or published_axis_model()
    if model.B.shape[1] != 1 or model.C.shape[0] != 1:
        raise ControllerSetupError("mpc: the servo MPC expects one input (current) and one output")
    A, B, C = velocity_form(model)
    n_x, hp, hu, ht = A.shape[0], config.hp, config.hu, config.ht
    Psi, Theta = prediction_matrices(A, B, C, hp, hu)
    Tr = reference_expansion(ht, hp, config.ert)
    Qd = np.diag(_weights(config.q, hp, "q", strict=False))
    Rd = np.diag(_weights(config.r, hu, "r", strict=True))
    H = 2.0 * (Theta.T @ Qd @ Theta + Rd)
    H = 0.5 * (H + H.T)
    F = np.vstack([2.0 * Psi.T @ Qd @ Theta, np.zeros((1, hu)), -2.0 * Tr.T @ Qd @ Theta])

    n_theta = n_x + 1 + ht
    L = np.tril(np.ones((hu, hu)))
    G_rows, W_rows, X_rows = [], [], []

    def add(G: np.ndarray, W: float, X: np.ndarray) -> None:
        G_rows.append(G)
        W_rows.append(np.full(G.shape[0], W))
        X_rows.append(X)

    u_col = np.zeros((hu, n_theta))
    u_col[:, n_x] = 1.0
    add(L, config.u_max, -u_col)  # u(k-1) + L ΔU <= u_max
    add(-L, -config.u_min, u_col)
    no_theta = np.zeros((hu, n_theta))
    if config.du_max is not None:
        add(np.eye(hu), config.du_max, no_theta)
    if config.du_min is not None:
        add(-np.eye(hu), -config.du_min, no_theta)
    output_rows = 0
    psi_cols = np.zeros((hp, n_theta))
    psi_cols[:, :n_x] = Psi
    if config.y_max is not None:
        add(Theta, config.y_max, -psi_cols)  # Ψx + ΘΔU <= y_max
        output_rows += hp
    if config.y_min is not None:
        add(-Theta, -config.y_min, psi_cols)
        output_rows += hp
    return CondensedQP(H=H, F=F, G=np.vstack(G_rows), W=np.concatenate(W_rows),
                       X=np.vstack(X_rows), Psi=Psi, Theta=Theta, ref_expansion=Tr, n_x=n_x,
                       output_rows=output_rows)


REFERENCE_BLOCK = 1024  # reference samples evaluated at once (vectorised), ticks


class QpSolver(Protocol):
    """What :class:`TrajectoryMpc` solves each tick with: θ -> ΔU (H_u moves)."""

    def solve(self, theta: np.ndarray) -> np.ndarray: ...


class DaqpSolver:
    """Online solver of the condensed QP: unconstrained fast path, else daqp (active set).

    ``last_path`` tells how the last problem was solved: "unconstrained", "qp", or
    "fallback" (daqp failed, e.g. infeasible output constraints: solved again without them,
    or the previous input held when even that fails). ``counts`` tallies the paths.
    """

    def __init__(self, qp: CondensedQP) -> None:
        self.qp = qp
        chol = sla.cho_factor(qp.H)
        K = -sla.cho_solve(chol, qp.F.T)  # unconstrained optimum ΔU = K θ
        # one product per tick gives the unconstrained ΔU, the constraints' θ part and the
        # linear cost term: [K; X; F'] θ
        self._stacked = np.ascontiguousarray(np.vstack([K, qp.X, qp.F.T]))
        self._rows = (K.shape[0], K.shape[0] + qp.X.shape[0])
        self._G, self._W = qp.G, qp.W
        self._W_tol = qp.W + FEASIBILITY_TOL
        rows = qp.G.shape[0]
        self._lhs, self._rhs = np.empty(rows), np.empty(rows)
        self._holds = np.empty(rows, dtype=bool)
        self._model = self._setup(qp.G)
        n_in = qp.G.shape[0] - qp.output_rows
        self._fallback = self._setup(qp.G[:n_in]) if qp.output_rows else None
        self._n_in = n_in
        self.last_path = ""
        self.counts = {"unconstrained": 0, "qp": 0, "fallback": 0}

    def _setup(self, G: np.ndarray) -> daqp.Model:
        model = daqp.Model()
        hu = self.qp.H.shape[0]
        rows = G.shape[0]
        exitflag, _ = model.setup(self.qp.H, np.zeros(hu), np.ascontiguousarray(G),
                                  np.full(rows, 1e30), np.full(rows, -1e30))
        if exitflag < 0:
            raise ControllerSetupError(f"mpc: daqp setup failed (exit flag {exitflag})")
        return model

    def solve(self, theta: np.ndarray) -> np.ndarray:
        """ΔU (H_u moves) minimising (9) subject to (13) for parameter vector ``theta``."""
        z = self._stacked @ theta
        hu, n_bound = self._rows
        dU, x_part, f = z[:hu], z[hu:n_bound], z[n_bound:]
        # G ΔU <= W + X θ (+ tolerance): ufuncs into buffers, no temporaries
        lhs, rhs, holds = self._lhs, self._rhs, self._holds
        np.matmul(self._G, dU, out=lhs)
        np.add(self._W_tol, x_part, out=rhs)
        np.less_equal(lhs, rhs, out=holds)
        if np.logical_and.reduce(holds):
            self.last_path = "unconstrained"
            self.counts["unconstrained"] += 1
            return dU
        bound = self._W + x_part
        x = self._solve_qp(self._model, f, bound)
        if x is not None:
            self.last_path = "qp"
            self.counts["qp"] += 1
            return x
        self.last_path = "fallback"
        self.counts["fallback"] += 1
        if self._fallback is not None:
            x = self._solve_qp(self._fallback, f, bound[: self._n_in])
            if x is not None:
                return x
        return np.zeros_like(dU)

    @staticmethod
    def _solve_qp(model: daqp.Model, f: np.ndarray, bound: np.ndarray) -> np.ndarray | None:
        """daqp's optimum, or None when it finds no optimum. ``update`` itself reports an
        infeasibility it detects (and ``solve`` would then return stale data as optimal)."""
        if model.update(f=f, bupper=bound) < 0:
            return None
        x, _, exitflag, _ = model.solve()
        return np.asarray(x) if exitflag >= 1 else None


class CvxpyReferenceSolver:
    """The same MPC problem written directly in cvxpy: the reference the tests compare to.

    Independent of :func:`condense`: the predicted states are rolled forward with the
    velocity-form model, the ERT is written from its definition, constraints (10)-(12) as
    stated. Compiled once (DPP); each :meth:`solve` only sets the parameters.
    """

    # Clarabel's default tolerances (1e-8) leave ~0.05 mA of error in the flat directions of H
    # (eigenvalues ~2 from R next to ~80): tightened so the reference is the accurate one.
    SOLVER_OPTIONS: ClassVar[dict[str, float]] = {
        "tol_gap_abs": 1e-12, "tol_gap_rel": 1e-12, "tol_feas": 1e-12, "tol_ktratio": 1e-10}

    def __init__(self, config: MpcConfig, model: StateSpaceModel | None = None) -> None:
        import cvxpy as cp  # heavy import, only where the reference is used

        A, B, C = velocity_form(model or published_axis_model())
        c = config
        q = _weights(c.q, c.hp, "q", strict=False)
        rw = _weights(c.r, c.hu, "r", strict=True)
        self._x0 = cp.Parameter(A.shape[0])
        self._u_prev = cp.Parameter()
        self._r = cp.Parameter(c.ht)
        self._dU = cp.Variable(c.hu)
        x = self._x0
        cost = cp.sum(cp.multiply(rw, cp.square(self._dU)))
        constraints = []
        for i in range(1, c.hp + 1):
            du = self._dU[i - 1] if i <= c.hu else 0.0
            x = A @ x + B[:, 0] * du
            y = C[0] @ x
            cost += q[i - 1] * cp.square(y - self._ref(i, c))
            if c.y_max is not None:
                constraints.append(y <= c.y_max)
            if c.y_min is not None:
                constraints.append(y >= c.y_min)
        u = self._u_prev + cp.cumsum(self._dU)
        constraints += [u <= c.u_max, u >= c.u_min]
        if c.du_max is not None:
            constraints.append(self._dU <= c.du_max)
        if c.du_min is not None:
            constraints.append(self._dU >= c.du_min)
        self.problem = cp.Problem(cp.Minimize(cost), constraints)
        self._nx = A.shape[0]

    def _ref(self, i: int, c: MpcConfig) -> Any:
        """r(i|k) for i <= H_t-2, else the ERT r̂(i|k) (paper, section II)."""
        r, ht = self._r, c.ht
        if i <= ht - 2:
            return r[i - 1]
        if c.ert == "zoh":
            return r[min(i, ht) - 1]
        return r[ht - 2] + (i - ht + 1) * (r[ht - 1] - r[ht - 2])

    def solve(self, theta: np.ndarray) -> np.ndarray:
        nx = self._nx
        self._x0.value = np.asarray(theta[:nx], dtype=float)
        self._u_prev.value = float(theta[nx])
        self._r.value = np.asarray(theta[nx + 1:], dtype=float)
        self.problem.solve(solver="CLARABEL", **self.SOLVER_OPTIONS)
        if self.problem.status != "optimal" or self._dU.value is None:
            raise SolverError(f"mpc: cvxpy reference failed ({self.problem.status})")
        return np.asarray(self._dU.value, dtype=float)


def prediction_map(qp: CondensedQP, config: MpcConfig) -> np.ndarray:
    """M with [û(0..H_p-1|k); ŷ(1..H_p|k)] = M [x̂(k|k); u(k-1); ΔU]: the inputs are u(k-1)
    plus the moves so far (held after H_u), the outputs Ψ x̂ + Θ ΔU."""
    n_x, hp, hu = qp.n_x, config.hp, config.hu
    moves = np.tril(np.ones((hp, hu)))  # row i sums the moves 0..min(i, H_u - 1)
    return np.block([[np.zeros((hp, n_x)), np.ones((hp, 1)), moves],
                     [qp.Psi, np.zeros((hp, 1)), qp.Theta]])


class TrajectoryMpc:
    """The MPC controller (a :class:`hil.controllers.base.ServoController`):
    ``step(position_deg, t_s) -> current_mA`` once per tick.

    Per tick: unwrap the measured position, correct the Kalman estimate, build θ from the
    estimate, the last current and the next H_t reference samples, solve, apply
    u(k) = u(k-1) + Δu(0|k), and propagate the estimate with that Δu.
    """

    def __init__(self, reference: Reference, config: MpcConfig | None = None,
                 model: StateSpaceModel | None = None, kalman: KalmanTuning | None = None,
                 solver: str = "daqp") -> None:
        self.config = config or MpcConfig()
        self.model = model or published_axis_model()
        self.reference = reference
        self.dt = self.model.dt
        self.qp = condense(self.config, self.model)
        A, B, C = velocity_form(self.model)
        self.kalman = SteadyStateKalman(A, B, C, kalman)
        if solver == "daqp":
            self.solver: QpSolver = DaqpSolver(self.qp)
        elif solver == "cvxpy":
            self.solver = CvxpyReferenceSolver(self.config, self.model)
        else:
            raise ControllerSetupError(f"mpc: solver must be 'daqp' or 'cvxpy', got {solver!r}")
        self._position = AngleUnwrapper()
        self._ref_anchor = AngleUnwrapper()
        self._theta = np.zeros(self.qp.n_theta)
        self._offsets = self.dt * np.arange(1, self.config.ht + 1)
        self._block_first = -1
        self._block = np.empty(0)
        self._prediction_matrix = prediction_map(self.qp, self.config)
        self._prediction_input = np.empty(self._prediction_matrix.shape[1])
        self.reset()

    def reset(self) -> None:
        """Forget the estimate and the last input (axis assumed at rest, zero current)."""
        self._position.reset()
        self._ref_anchor.reset()
        self._u = 0.0
        self._started = False
        self._dU = np.zeros(self.config.hu)
        self._theta[:] = 0.0

    def _reference_ahead(self, t: float) -> tuple[np.ndarray, bool]:
        """r(t + i T), i = 1..H_t, and whether they wrap 360 -> 0 (a step of 180 deg or more).
        On the sample grid (t = k T, as the loop calls) both come from a block of
        ``REFERENCE_BLOCK`` ticks evaluated at once."""
        k = round(t / self.dt)
        if abs(k * self.dt - t) > 1e-9 * max(1.0, abs(t)):
            raw = np.asarray(self.reference.position(t + self._offsets), dtype=float)
            return raw, bool(raw.size > 1 and np.abs(raw[1:] - raw[:-1]).max() >= 180.0)
        first = k - k % REFERENCE_BLOCK
        if first != self._block_first:
            self._load_block(first)
        i = k - first
        return self._block[i:i + self.config.ht], bool(self._wraps[i])

    def _load_block(self, first: int) -> None:
        """The reference samples of ticks ``first + 1 ..`` and, for each window start in
        them, whether that window wraps 360 -> 0 (a step of 180 deg or more in it)."""
        ht = self.config.ht
        ticks = first + 1 + np.arange(REFERENCE_BLOCK + ht)
        self._block = np.asarray(self.reference.position(ticks * self.dt), dtype=float)
        self._block_first = first
        big = np.abs(self._block[1:] - self._block[:-1]) >= 180.0
        ends = np.concatenate([[0], np.cumsum(big)])  # big steps before each sample
        starts = np.arange(REFERENCE_BLOCK)
        self._wraps = ends[starts + ht - 1] > ends[starts]

    def reference_window(self, window: np.ndarray, t: float, near: float) -> np.ndarray:
        """r(1..H_t|k) as continuous angles, anchored within ±180 deg of ``near`` at first,
        written into ``window`` (the tick's θ: no new array)."""
        raw, wraps = self._reference_ahead(t)
        raw0 = float(raw[0])
        first = self._ref_anchor.update(raw0, near=near)
        np.add(raw, first - raw0, out=window)
        if wraps:  # the window itself wraps 360 -> 0
            steps = raw[1:] - raw[:-1]
            window[1:] = first + np.cumsum((steps + 180.0) % 360.0 - 180.0)
        return window

    def step(self, position_deg: float, t_s: float) -> float:
        """Current command [mA] for the measured position [deg] at time ``t_s`` [s]."""
        n_x = self.qp.n_x
        y = self._position.update(float(position_deg))
        if not self._started:
            x0 = np.zeros(n_x)
            x0[-1] = y
            self.kalman.reset(x0)
            self._started = True
        theta = self._theta
        self.kalman.update(y, out=theta[:n_x])
        theta[n_x] = self._u
        self.reference_window(theta[n_x + 1:], t_s, near=y)
        self._dU = self.solver.solve(theta)
        u = min(max(self._u + float(self._dU[0]), self.config.u_min), self.config.u_max)
        self.kalman.predict(u - self._u)
        self._u = u
        return u

    def prediction(self) -> tuple[np.ndarray, np.ndarray]:
        """Predicted inputs û(0..H_p-1|k) [mA] and outputs ŷ(1..H_p|k) [deg, continuous frame]
        of the last step (for waterfall plots like Figs. 9-10)."""
        n_x, hp = self.qp.n_x, self.config.hp
        given = self._prediction_input
        given[: n_x + 1] = self._theta[: n_x + 1]
        given[n_x + 1:] = self._dU
        z = self._prediction_matrix @ given
        return z[:hp], z[hp:]

    # -- parameters changed while it runs (hil.controllers.base.Tunable, Rebuilding) ---------
    def tunables(self) -> list[TunableParam]:
        """The horizons, the scalar weights and the current bound, in force now: each
        changes the QP, so each is rebuilt off the loop and swapped in at a tick boundary."""
        c = self.config
        params = [
            TunableParam("ht", c.ht, "ticks", 1, 200, 1, rebuild=True,
                         description="trajectory horizon H_t (<= H_p)"),
            TunableParam("hu", c.hu, "ticks", 1, 200, 1, rebuild=True,
                         description="control horizon H_u (<= H_p)"),
            TunableParam("hp", c.hp, "ticks", 1, 200, 1, rebuild=True,
                         description="prediction horizon H_p"),
            TunableParam("umax", c.u_max, "mA", 0.0, 32_767.0, 10.0, rebuild=True,
                         description="current bound |u| <= umax"),
        ]
        for name, value, what in (("q", c.q, "output weight Q"), ("r", c.r, "input weight R")):
            if isinstance(value, (int, float)):
                params.append(TunableParam(name, float(value), "", 0.0, 1e12, None,
                                           rebuild=True, description=what))
        return params

    def set_tunable(self, name: str, value: Any) -> None:
        """Every parameter of the MPC needs a rebuild: :meth:`rebuilt`."""
        raise ControllerSetupError(f"mpc: {name} is applied by a rebuild")

    def rebuilt(self, name: str, value: Any) -> Callable[[], None]:
        """The QP and solver for ``name = value``, built now (off the loop); the returned swap
        puts them in place keeping the estimate, the unwrapped position and the last
        current, and carries the solver's counts over."""
        changes: dict[str, Any] = {"u_min": -float(value), "u_max": float(value)} \
            if name == "umax" else {name: value}
        if name not in ("ht", "hu", "hp", "umax", "q", "r"):
            raise ControllerSetupError(f"mpc: no tunable parameter {name!r}")
        solver = "cvxpy" if isinstance(self.solver, CvxpyReferenceSolver) else "daqp"
        fresh = TrajectoryMpc(self.reference, replace(self.config, **changes), self.model,
                              solver=solver)

        def swap() -> None:
            kept = (self._position, self._ref_anchor, self.kalman, self._u, self._started)
            counts = getattr(self.solver, "counts", {})
            self.__dict__.update(fresh.__dict__)
            self._position, self._ref_anchor, self.kalman, self._u, self._started = kept
            new_counts = getattr(self.solver, "counts", None)
            if isinstance(new_counts, dict):
                for path, count in counts.items():
                    new_counts[path] = new_counts.get(path, 0) + count
        return swap
