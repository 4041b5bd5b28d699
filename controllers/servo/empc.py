"""Explicit MPC (servo paper, eq. 15 and sections III-C/D): the trajectory MPC of
:mod:`hil.controllers.servo.mpc` solved offline as a piecewise-affine law over a box of parameters,
searched online through a binary tree, with the online QP as fallback outside the box.

Parameters. The MPC's θ = [Δx_p; y; u(k-1); r(1|k) .. r(H_t|k)] (n + 1 + 1 + H_t values) is
shift invariant when only u and Δu are constrained: adding c to y and to every r(i) moves
every predicted output and every reference by c (the rows of Ψ for y and of the ERT matrix
sum to one), so the cost and the optimum do not change. The law therefore depends on one
parameter less, the *relative* coordinates

    φ = [Δx_p,1 .. Δx_p,n;  u(k-1);  e = r(1|k) - y;  dr_i = r(i|k) - r(i-1|k), i = 2..H_t]

(names ``dx1``..``dxn``, ``u``, ``e``, ``dr2``..): the tracking error one tick ahead and
the reference steps per tick. Besides removing a dimension this makes the box meaningful on a
modulo axis (absolute positions grow without bound, errors and speeds do not) and keeps the
numbers small. Output constraints (y limits) break the invariance and are refused.

Default box (published axis, T = 500 us, |u| <= 1000 mA), half-widths around 0:

=====  ===========  ==========================================================================
dx1    10 rad/s     motor-speed change per tick: the largest any input within ±2200 mA (the
                    1000 mA limit plus a Fig. 16-size 1200 mA disturbance) can cause on the
                    model, 9.5 (ℓ1 norm of the increment's impulse response, i.e. the
                    resonance driven at its frequency); the paper's scenarios stay below 0.2
dx2    3 rad/s      load-speed change per tick, same bound (2.6)
dx3/4  0.06 rad     motor/load angle change per tick: 0.06 rad per 500 us ≈ 1150 rpm
e      180 deg      the largest error that means anything on a modulo axis (Fig. 16: 23 deg)
dr     3 deg        reference step per tick: 6000 deg/s = 1000 rpm (the paper's move: 60 rpm)
u      limits       u(k-1) in [u_min, u_max]: always true, the output is clipped there
=====  ===========  ==========================================================================

The box is generous on purpose: on a drive there is no online QP to fall back on, and the
region count does not grow with the box once every reachable active set has a region in it
(H_t = H_u = 3, H_p = 50: 21 regions and 11 controllers, the most there can be: of the
3^3 patterns of u(i|k) at its upper limit, lower limit or free, the 6 with u(0|k) and u(1|k)
at opposite limits are never optimal. A box tight around the paper's scenarios, e.g.
dx1=dx2=1, dx3=dx4=0.02, e=30, dr=1, gives 19 regions and 9 controllers: the two patterns with
u(1|k) and u(2|k) at opposite limits need a strongly excited resonance).

Controllers. Regions whose first move Δu(0|k) follows the same affine law share one
*controller* (eq. 15: M_i θ + m_i, what the drive applies); the tree separates controllers,
not regions. Controller 0 is the unconstrained law (the paper's controller #1).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from hil.controllers.errors import ControllerSetupError
from hil.controllers.servo.empc_tree import (
    OUTSIDE_BOX,
    Polyhedron,
    SearchTree,
    TreeEvaluator,
    build_tree,
)
from hil.controllers.servo.kalman import KalmanTuning
from hil.controllers.servo.model import StateSpaceModel, published_axis_model
from hil.controllers.servo.mpc import CondensedQP, MpcConfig, QpSolver, TrajectoryMpc, condense
from hil.controllers.servo.mpqp import MpQP, MpqpSolution, solve_mpqp
from hil.controllers.servo.references import Reference

DEFAULT_HALF_WIDTHS = {"dx1": 10.0, "dx2": 3.0, "dx3": 0.06, "dx4": 0.06, "e": 180.0, "dr": 3.0}


def parameter_names(n_states: int, ht: int) -> list[str]:
    return ([f"dx{i + 1}" for i in range(n_states)] + ["u", "e"]
            + [f"dr{i}" for i in range(2, ht + 1)])


def relative_map(qp: CondensedQP, ht: int) -> tuple[np.ndarray, np.ndarray]:
    """P with φ = P θ, and S with θ = S φ (the θ of φ with y = 0), for the module's φ."""
    n = qp.n_x - 1
    n_phi = n + 1 + ht
    P = np.zeros((n_phi, qp.n_theta))
    S = np.zeros((qp.n_theta, n_phi))
    y, u, r0 = n, n + 1, n + 2
    for i in range(n):
        P[i, i] = S[i, i] = 1.0
    P[n, u] = S[u, n] = 1.0
    P[n + 1, r0] = 1.0
    P[n + 1, y] = -1.0
    for i in range(1, ht):
        P[n + 1 + i, r0 + i] = 1.0
        P[n + 1 + i, r0 + i - 1] = -1.0
    for j in range(ht):  # r(j+1) = e + dr_2 + .. + dr_(j+1)
        S[r0 + j, n + 1: n + 2 + j] = 1.0
    return P, S


def _check_shift_invariance(qp: CondensedQP) -> None:
    d = np.zeros(qp.n_theta)
    d[qp.n_x - 1] = 1.0
    d[qp.n_x + 1:] = 1.0
    scale = np.abs(qp.F).max()
    if qp.output_rows or np.abs(qp.X @ d).max() > 0 or np.abs(qp.F.T @ d).max() > 1e-9 * scale:
        raise ControllerSetupError(
            "empc: the explicit MPC needs a shift-invariant problem (input and "
   "input-rate constraints only); output limits y_min/y_max are not "
   "supported")


@dataclass(frozen=True)
class ParameterBox:
    """Bounds of the relative parameters φ (see the module doc)."""

    names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray

    def as_dict(self) -> dict[str, list[float]]:
        return {n: [float(lo), float(hi)]
                for n, lo, hi in zip(self.names, self.lower, self.upper, strict=True)}


def parameter_box(config: MpcConfig, n_states: int,
                  spec: str | Mapping[str, Any] | None = None) -> ParameterBox:
    """The default box, changed by ``spec`` (``"e=30,dr=1"`` or a mapping name -> half-width
    or (lo, hi)); ``scale`` multiplies every default half-width except u's."""
    names = parameter_names(n_states, config.ht)
    items = _box_items(spec)
    scale = items.pop("scale", 1.0)
    if isinstance(scale, tuple) or not scale > 0:
        raise ControllerSetupError(f"empc box: scale must be a positive number, got {scale}")
    defaults = dict(DEFAULT_HALF_WIDTHS)
    if n_states != 4:  # the dx defaults describe the published 4-state axis only
        defaults = {k: v for k, v in defaults.items() if not k.startswith("dx")}
    lower = np.empty(len(names))
    upper = np.empty(len(names))
    for i, name in enumerate(names):
        value: float | tuple[float, float]
        if name in items:
            value = items[name]
        elif name.startswith("dr") and "dr" in items:
            value = items["dr"]
        elif name == "u":
            value = (config.u_min, config.u_max)
        else:
            base = defaults.get("dr" if name.startswith("dr") else name)
            if base is None:
                raise ControllerSetupError(f"empc box: no default for {name} on a {n_states}-state "
                                  f"model; give {', '.join(names[:n_states])} in the box")
            value = base * scale
        lo, hi = value if isinstance(value, tuple) else (-value, value)
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ControllerSetupError(f"empc box: {name} needs a finite interval lo < hi, got "
                              f"{lo}:{hi}")
        lower[i], upper[i] = lo, hi
    u = names.index("u")
    if lower[u] < config.u_min or upper[u] > config.u_max:
        raise ControllerSetupError(f"empc box: u must lie within the current limits "
                          f"[{config.u_min:g}, {config.u_max:g}] mA")
    unknown = set(items) - set(names) - {"dr"}
    if unknown:
        raise ControllerSetupError(f"empc box: unknown parameter(s) {', '.join(sorted(unknown))}; "
                          f"known: {', '.join(names)}, dr, scale")
    return ParameterBox(tuple(names), lower, upper)


def _box_items(spec: str | Mapping[str, Any] | None) -> dict[str, Any]:
    if spec is None:
        return {}
    if isinstance(spec, Mapping):
        return {k: (tuple(map(float, v)) if isinstance(v, (tuple, list)) else float(v))
                for k, v in spec.items()}
    items: dict[str, Any] = {}
    for item in filter(None, (part.strip() for part in spec.split(","))):
        name, eq, text = item.partition("=")
        name = name.strip()
        if not eq or not name:
            raise ControllerSetupError(f"empc box: expected NAME=VALUE, got {item!r}")
        try:
            if ":" in text:
                lo, hi = text.split(":", 1)
                items[name] = (float(lo), float(hi))
            else:
                half = float(text)
                if not half > 0:
                    raise ControllerSetupError(
                        f"empc box: {name} half-width must be > 0, got {half}")
                items[name] = half
        except ValueError:
            raise ControllerSetupError(f"empc box: {name}: not a number or LO:HI range: "
                              f"{text!r}") from None
    return items


@dataclass(frozen=True)
class ExplicitLaw:
    """The explicit MPC: regions over the box (in φ), controllers, search tree.

    ``gains[c] @ φ + offsets[c]`` is Δu(0|k) of controller c; ``labels[i]`` the controller
    of region i.
    """

    config: MpcConfig
    qp: CondensedQP
    box: ParameterBox
    P: np.ndarray
    solution: MpqpSolution
    labels: np.ndarray
    gains: np.ndarray
    offsets: np.ndarray
    tree: SearchTree
    build_s: float

    @property
    def n_controllers(self) -> int:
        return int(self.gains.shape[0])

    @cached_property
    def evaluator(self) -> TreeEvaluator:
        """Tree descent returning (controller, Δu(0|k)) from φ."""
        return TreeEvaluator(self.tree, self.gains, self.offsets)

    def phi(self, theta: np.ndarray) -> np.ndarray:
        return self.P @ theta

    def first_move(self, theta: np.ndarray) -> tuple[int, float]:
        """(controller index, Δu(0|k)), or (NOT_FOUND / OUTSIDE_BOX, nan)."""
        return self.evaluator.law(self.P @ theta)

    def moves(self, theta: np.ndarray) -> np.ndarray | None:
        """All H_u optimal moves from the region containing θ (sequential search), or None."""
        return self.solution.optimiser(self.P @ theta)

    def summary(self) -> dict[str, Any]:
        """The figures ``hil empc build`` prints."""
        c = self.config
        return {
            "regions": len(self.solution.regions),
            "controllers": self.n_controllers,
            "tree_nodes": self.tree.nodes,
            "tree_depth": self.tree.depth,
            "build_s": round(self.build_s, 3),
            "tree_leaves": self.tree.leaves,
            "hyperplanes": self.tree.planes_used,
            "mpqp_s": round(self.solution.build_s, 3),
            "tree_s": round(self.tree.build_s, 3),
            "ht": c.ht, "hu": c.hu, "hp": c.hp, "ert": c.ert,
            "u_min": c.u_min, "u_max": c.u_max,
            "parameters": list(self.box.names),
            "box": self.box.as_dict(),
        }


MAX_EXPLICIT_HU = 6  # 3^6 active sets: about a minute to build; H_u = 8 does not finish


def build_explicit_law(config: MpcConfig, model: StateSpaceModel | None = None,
                       box: str | Mapping[str, Any] | ParameterBox | None = None,
                       ) -> ExplicitLaw:
    """Solve the mpQP of the MPC over the box and build the search tree of its controllers."""
    if config.hu > MAX_EXPLICIT_HU:
        raise ControllerSetupError(
            f"empc: H_u = {config.hu} is too large for an explicit solution (enumerated over "
            f"3^H_u active sets); H_u <= {MAX_EXPLICIT_HU} is supported (the paper runs H_u = 3)")
    start = time.perf_counter()
    model = model or published_axis_model()
    qp = condense(config, model)
    _check_shift_invariance(qp)
    if not isinstance(box, ParameterBox):
        box = parameter_box(config, qp.n_x - 1, box)
    P, S = relative_map(qp, config.ht)
    problem = MpQP(H=qp.H, F=S.T @ qp.F, G=qp.G, W=qp.W, X=qp.X @ S,
                   lower=box.lower, upper=box.upper)
    solution = solve_mpqp(problem)
    if not solution.regions:
        raise ControllerSetupError("empc: no critical region in the box (is the problem feasible?)")
    labels = solution.law_labels(slice(0, 1))
    first = [int(np.flatnonzero(labels == c)[0]) for c in range(int(labels.max()) + 1)]
    gains = np.array([solution.regions[i].K[0] for i in first])
    offsets = np.array([solution.regions[i].k[0] for i in first])
    polyhedra = [Polyhedron(r.A, r.b, r.boundary) for r in solution.regions]
    tree = build_tree(polyhedra, labels, box.lower, box.upper, covered=solution.covers_box)
    return ExplicitLaw(config=config, qp=qp, box=box, P=P, solution=solution, labels=labels,
                       gains=gains, offsets=offsets, tree=tree,
                       build_s=time.perf_counter() - start)


class ExplicitSolver:
    """Stands in for :class:`DaqpSolver` inside :class:`TrajectoryMpc`: Δu(0|k) from the tree
    and the controller's law; the online QP when θ is outside the box (or in a hole).

    The tree gives the first move only (what is applied); the later moves of the returned
    vector are NaN (:meth:`ExplicitMpc.prediction` recomputes them). ``last_path`` is
    "explicit" or "fallback", ``last_reason`` "outside_box" or "no_region" after a fallback.
    """

    def __init__(self, law: ExplicitLaw, online: QpSolver) -> None:
        self.law = law
        self.online = online
        self._P = np.ascontiguousarray(law.P)
        self._tree = law.evaluator
        self._unknown = np.full(law.config.hu, np.nan)
        self.last_path = ""
        self.last_reason = ""
        self.last_controller = -1
        self.counts = {"explicit": 0, "fallback": 0}

    def solve(self, theta: np.ndarray) -> np.ndarray:
        code, du0 = self._tree.law(self._P @ theta)
        self.last_controller = code
        if code >= 0:
            self.last_path = "explicit"
            self.counts["explicit"] += 1
            dU = self._unknown.copy()
            dU[0] = du0
            return dU
        self.last_path = "fallback"
        self.last_reason = "outside_box" if code == OUTSIDE_BOX else "no_region"
        self.counts["fallback"] += 1
        return self.online.solve(theta)


class ExplicitMpc(TrajectoryMpc):
    """:class:`TrajectoryMpc` with the explicit law in place of the online QP.

    Same ``step(position_deg, t_s) -> mA``, ``reset()`` and ``prediction()``. Build it with the
    same arguments as the online MPC plus ``box`` (see :func:`parameter_box`), or pass a
    prebuilt ``law`` (:func:`build_explicit_law`, for the same config and model) to skip the
    offline solve. Each tick solved online is counted in ``fallbacks``; entering and leaving
    the fallback are recorded in ``events`` (dicts with ``t_s``, ``kind`` "empc_fallback" /
    "empc_resume", ``reason``, and the out-of-box coordinates), which :meth:`pop_events`
    hands to a runner for its event log.
    """

    def __init__(self, reference: Reference, config: MpcConfig | None = None,
                 model: StateSpaceModel | None = None, kalman: KalmanTuning | None = None,
                 box: str | Mapping[str, Any] | ParameterBox | None = None,
                 law: ExplicitLaw | None = None) -> None:
        self.events: list[dict[str, Any]] = []
        self.fallbacks = 0
        self._fallback_ticks = 0
        super().__init__(reference, config, model, kalman, solver="daqp")
        if law is None:
            law = build_explicit_law(self.config, self.model, box)
        elif law.config != self.config or not (
                np.array_equal(law.qp.F, self.qp.F) and np.array_equal(law.qp.H, self.qp.H)):
            raise ControllerSetupError(
                "empc: the prebuilt explicit law is for another MPC config or "
       "model")
        self.law = law
        self.explicit = ExplicitSolver(law, self.solver)
        self.solver = self.explicit

    def reset(self) -> None:
        super().reset()
        self.events = []
        self.fallbacks = 0
        self._fallback_ticks = 0

    def step(self, position_deg: float, t_s: float) -> float:
        u = super().step(position_deg, t_s)
        solver = self.explicit
        if solver.last_path == "fallback":
            self.fallbacks += 1
            if self._fallback_ticks == 0:
                self.events.append(self._fallback_event(t_s, solver.last_reason))
            self._fallback_ticks += 1
        elif self._fallback_ticks:
            self.events.append({"t_s": t_s, "kind": "empc_resume", "level": "info",
                                "message": f"back in the explicit law after "
                                           f"{self._fallback_ticks} online ticks",
                                "ticks": self._fallback_ticks})
            self._fallback_ticks = 0
        return u

    def _fallback_event(self, t_s: float, reason: str) -> dict[str, Any]:
        phi = self.law.phi(self._theta)
        box = self.law.box
        outside = {name: float(v) for name, v, lo, hi
                   in zip(box.names, phi, box.lower, box.upper, strict=True)
                   if not lo <= v <= hi}
        what = ", ".join(f"{k}={v:.4g}" for k, v in outside.items()) or "inside the box"
        return {"t_s": t_s, "kind": "empc_fallback", "level": "warning", "reason": reason,
                "message": f"explicit MPC: {reason.replace('_', ' ')} ({what}); "
                           "solving the QP online", "outside": outside}

    def pop_events(self) -> list[dict[str, Any]]:
        """The events since the last call (and forget them)."""
        events, self.events = self.events, []
        return events

    def prediction(self) -> tuple[np.ndarray, np.ndarray]:
        if self.explicit.last_path == "explicit":
            moves = self.law.moves(self._theta)
            self._dU = moves if moves is not None else self.explicit.online.solve(self._theta)
        return super().prediction()
