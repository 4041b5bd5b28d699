"""What a relay plan costs over one horizon of the EEC, as its solvers share it.

:class:`HorizonCosts` holds the weights of J (eq. 4, the limit term, ``gamma3``), the J1
coefficients of each decision, the step peaks of every combination of the peripherals' local
states (off, on, starting) and the level bounds a plan must keep, and evaluates plans with
them: their cost, their predicted power.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from hil.controllers.bench.eec_settings import EECSettings
from hil.controllers.bench.prediction import HorizonPrediction
from hil.controllers.bench.problem import BenchProblem


class HorizonCosts:
    """The costs and level bounds of the relay plans of one horizon (built once)."""

    def __init__(self, prediction: HorizonPrediction, problem: BenchProblem,
                 settings: EECSettings) -> None:
        self.p = prediction
        self.problem = problem
        self.settings = settings
        self.nd = len(problem.peripherals)
        self.H = prediction.steps
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
        # (peripherals, H, 3): the cost of each step spent off, on, starting
        self.class_costs = np.stack([np.stack([np.zeros(self.H), self.w1 * self.area_u[j],
                                               self.w1 * self.area_u[j] + self.start_cost[j]],
                                              axis=1) for j in range(self.nd)])

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

    def predicted_power(self, u: np.ndarray, u_prev: np.ndarray, free: np.ndarray
                        ) -> np.ndarray:
        """Predicted S at every fine row for relay plan ``u`` (exact, no rounding)."""
        prev = np.concatenate([np.asarray(u_prev, float)[:, None], u[:, :-1]], axis=1)
        s = np.clip(u - prev, 0, None)
        return free + np.einsum("jrh,jh->r", self.Gu, u) + np.einsum("jrh,jh->r", self.Gs, s)
