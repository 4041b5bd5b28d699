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

The horizon problem lives in modules of its own: what a plan costs
(:mod:`~hil.controllers.bench.eec_costs`), the solver that plans a horizon
(:mod:`~hil.controllers.bench.eec_solver`) by the schedule DP (default,
:mod:`~hil.controllers.bench.eec_dp`) or the MILP (:mod:`~hil.controllers.bench.eec_milp`),
the previous plan repaired as the next one's start (:mod:`~hil.controllers.bench.eec_repair`),
the tuning (:mod:`~hil.controllers.bench.eec_settings`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hil.controllers.base import BenchObservation, TunableParam
from hil.controllers.bench.bc import hysteresis_rule
from hil.controllers.bench.eec_settings import EECSettings, SolveResult
from hil.controllers.bench.eec_solver import HorizonSolver
from hil.controllers.bench.kalman import BenchKalman, KalmanSettings
from hil.controllers.bench.prediction import BenchEstimate, BenchModels, HorizonPrediction
from hil.controllers.bench.problem import BenchProblem, DwellClock
from hil.controllers.errors import ControllerSetupError


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
        self.models = models
        self.problem = problem
        self.settings = settings
        spd = round(settings.step_s / models.dt)
        if abs(spd * models.dt - settings.step_s) > 1e-9:
            raise ValueError(f"decision step {settings.step_s} s is not a whole number of "
                             f"model samples ({models.dt} s)")
        self.prediction = HorizonPrediction(models, problem, settings.hp_steps, spd)
        self.solver = HorizonSolver(self.prediction, problem, settings)
        self.dwell = DwellClock.start(problem.peripherals, initial)
        self.plan: Plan | None = None
        self._plan_age = 0
        self._first = True
        self.feedback = feedback
        # rebuilt parts swapped in at the next decision: (settings, prediction, solver)
        self._next: tuple[EECSettings, HorizonPrediction, HorizonSolver] | None = None
        # first call of the cached model products outside the timed path
        self.prediction.free(BenchEstimate.at_rest(models))

    def decide(self, obs: BenchObservation) -> dict[str, bool]:
        """The relay command for ``obs`` (:meth:`step` tells how it was decided)."""
        return self.step(obs).relays

    def step(self, obs: BenchObservation) -> Decision:
        """Decide from ``obs``, whose ``estimate`` is a :class:`BenchEstimate`."""
        if self._next is not None:
            self._swap_in()
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
        result = self.solver.solve(free, u_prev, fixed, q0, t, warm, budget)
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
        horizon = self.solver.horizon
        power = horizon.predicted_power(result.u, u_prev, free).reshape(H, -1)
        q = np.empty((len(self.problem.resources), H + 1))
        for j, res in enumerate(self.problem.resources):
            rates = res.alpha * horizon.consumption(res.consumer, t) \
                + res.eta * step * result.u[j]
            q[j] = q0[j] + np.concatenate([[0.0], np.cumsum(rates)])
        return Plan(t, result.u, q, power.max(axis=1), float(power.max()),
                    float(power.sum() * self.prediction.dt), result.objective, result.status,
                    result.solve_ms, result.rows, result.gap, result.nodes, result.bound)

    # -- parameters changed while it runs (hil.controllers.base.Tunable, Rebuilding) ---------
    def tunables(self) -> list[TunableParam]:
        """The weights of J and the prediction horizon, in force now (or waiting for the next
        decision). Each changes the horizon's costs, built once per horizon: rebuilt off the
        loop, in place from the next decision on, the estimate and the dwell kept."""
        c = self._next[0] if self._next is not None else self.settings
        return [
            TunableParam("gamma1", c.gamma1, "", 0.0, 1e6, 0.05, rebuild=True,
                         description="weight of J1 (energy)"),
            TunableParam("gamma2", c.gamma2, "", 0.0, 1e6, 0.05, rebuild=True,
                         description="weight of J2 (peak)"),
            TunableParam("gamma3", c.gamma3, "", 0.0, 1e9, None, rebuild=True,
                         description="cost of one switch-on (relay wear), in units of J"),
            TunableParam("hp_s", round(c.hp_steps * c.step_s), "s", c.step_s, 3600.0, c.step_s,
                         rebuild=True, description="prediction horizon H_p"),
        ]

    def set_tunable(self, name: str, value: Any) -> None:
        """Every parameter of the EEC needs a rebuild: :meth:`rebuilt`."""
        raise ControllerSetupError(f"eec: {name} is applied by a rebuild")

    def rebuilt(self, name: str, value: Any) -> Callable[[], None]:
        """The costs (and, for ``hp_s``, the prediction) for ``name = value``, built now; the
        swap hands them to the next decision."""
        base = self._next[0] if self._next is not None else self.settings
        if name == "hp_s":
            steps = round(float(value) / base.step_s)
            if abs(steps * base.step_s - float(value)) > 1e-9:
                raise ControllerSetupError(f"eec: hp_s = {value:g} s is not a whole number of "
                                           f"decision steps ({base.step_s:g} s)")
            changes: dict[str, Any] = {"hp_steps": steps}
        elif name in ("gamma1", "gamma2", "gamma3"):
            changes = {name: float(value)}
        else:
            raise ControllerSetupError(f"eec: no tunable parameter {name!r}")
        try:
            settings = replace(base, **changes)
        except ValueError as exc:
            raise ControllerSetupError(f"eec: {exc}") from None
        prediction = self.prediction
        if settings.hp_steps != prediction.steps:
            prediction = HorizonPrediction(self.models, self.problem, settings.hp_steps,
                                           prediction.samples_per_step)
            prediction.free(BenchEstimate.at_rest(self.models))
        solver = HorizonSolver(prediction, self.problem, settings)

        def swap() -> None:
            self._next = (settings, prediction, solver)
        return swap

    def _swap_in(self) -> None:
        """The rebuilt parts, at a decision; a new horizon drops the plan (its warm start)."""
        assert self._next is not None
        settings, prediction, solver = self._next
        self._next = None
        if prediction is not self.prediction:
            self.plan = None
        self.settings, self.prediction, self.solver = settings, prediction, solver
