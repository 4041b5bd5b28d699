"""The EEC's prediction over its horizon, linear in the decisions (paper, eq. 7c).

Decisions are taken every ``step_s`` (1 s) for ``H`` steps: relay state ``u[j, i]`` of
peripheral j during step i and its switch-on event ``s[j, i]``. The total apparent power is
predicted on the model's fine grid (0.01 s, so the switch-on inrush is resolved inside each
step): row ``r`` is the meter reading ``r + 1`` samples after the decision instant, and

    S(r) = free(r) + sum_j ( Gu_j[r, :] u[j, :] + Gs_j[r, :] s[j, :] )

``free`` holds everything the decisions cannot change: the machining sequence's power (known
a priori) from the estimated machining state, the decay of each device's estimated state, the
base load and the estimated disturbance. ``Gu``, ``Gs`` are block Toeplitz (the models are time
invariant), so they are kept as a small coefficient block ``coef[m, j, kind, lag]``: the
coefficient of ``(u if kind == 0 else s)[j, i - lag]`` in the row at offset ``m`` of step ``i``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hil.controllers.bench.models import DeviceModel, MachiningModel
from hil.controllers.bench.problem import BenchProblem

#: coefficients smaller than this fraction of the device's steady power are dropped
COEF_RTOL = 1e-6


@dataclass(frozen=True)
class BenchModels:
    """Every load model of the bench, devices in the problem's peripheral order."""

    machining: MachiningModel
    devices: dict[str, DeviceModel]

    @property
    def dt(self) -> float:
        return self.machining.model.dt


@dataclass
class BenchEstimate:
    """The state the predictions start from (the Kalman filter's, or a simulation's).

    ``sample`` counts model samples since the machining sequence's origin; the states are
    those of sample ``sample`` (the latest meter reading), in the models' deviation coordinates.
    ``output_va`` and ``innovation_va`` are the filter's diagnostics at that sample (recorded,
    not used by the predictions).
    """

    sample: int
    x_machining: np.ndarray
    x_devices: dict[str, np.ndarray]
    disturbance_va: float = 0.0
    output_va: float = 0.0
    innovation_va: float = 0.0

    @classmethod
    def at_rest(cls, models: BenchModels, sample: int = 0) -> BenchEstimate:
        """Everything off and settled (what a controller assumes before any measurement)."""
        return cls(sample, np.zeros(models.machining.model.order),
                   {name: np.zeros(dev.model.order) for name, dev in models.devices.items()})


@dataclass
class HorizonPrediction:
    """Prediction structure for ``steps`` decision steps of ``samples_per_step`` samples."""

    models: BenchModels
    problem: BenchProblem
    steps: int
    samples_per_step: int
    coef: np.ndarray = field(init=False)  # (m, j, kind, lag index); lag = index - 1
    max_lag: int = field(init=False)

    def __post_init__(self) -> None:
        spd, H = self.samples_per_step, self.steps
        names = self.problem.peripherals
        # impulse responses long enough to cover the whole horizon
        n = H * spd + spd + 1
        pulses = []
        for name in names:
            g = self.models.devices[name].model.impulse(n)
            # response at row r (reading r+1 samples after the step start) to u held over
            # samples 0..spd-1 of the step, and to a switch-on event at sample 0
            cu = np.convolve(g[:, 0], np.ones(spd))[: n]
            pulses.append((cu, g[:, 1]))
        # rows of step i at offset m see decision i - lag through response index
        # m + 1 + spd * lag (the decision is applied at sample spd * (i - lag))
        lags = []
        for lag in range(-1, H):
            idx = np.arange(spd) + 1 + spd * lag
            if idx[-1] < 0:
                continue
            lags.append(lag)
        self.max_lag = 0
        coef = np.zeros((spd, len(names), 2, H + 1))
        for j, (cu, cs) in enumerate(pulses):
            tol = COEF_RTOL * max(self.models.devices[names[j]].steady_va, 1.0)
            for lag in lags:
                idx = np.arange(spd) + 1 + spd * lag
                valid = (idx >= 0) & (idx < n)
                for kind, resp in enumerate((cu, cs)):
                    col = np.zeros(spd)
                    col[valid] = resp[idx[valid]]
                    col[np.abs(col) < tol] = 0.0
                    coef[:, j, kind, lag + 1] = col
                    if np.any(col):
                        self.max_lag = max(self.max_lag, lag)
        self.coef = coef[:, :, :, : self.max_lag + 2]

    # -- sizes --------------------------------------------------------------------------
    @property
    def rows(self) -> int:
        return self.steps * self.samples_per_step

    @property
    def dt(self) -> float:
        return self.models.dt

    @property
    def step_s(self) -> float:
        return self.samples_per_step * self.models.dt

    # -- what the decisions cannot change ------------------------------------------------
    def free(self, est: BenchEstimate) -> np.ndarray:
        """Predicted total VA at rows 0..R-1 with every peripheral off from now on."""
        R = self.rows
        out = self.models.machining.predict(est.x_machining, est.sample, R)
        for name, device in self.models.devices.items():
            x = est.x_devices.get(name)
            if x is not None:
                out = out + device.model.observability(R) @ np.asarray(x, float)
        return out + est.disturbance_va

    # -- dense forms (reference formulations, tests) -------------------------------------
    def dense(self) -> tuple[np.ndarray, np.ndarray]:
        """(Gu, Gs), each (devices, R, H): S = free + sum_j Gu[j] u[j] + Gs[j] s[j]."""
        spd, H = self.samples_per_step, self.steps
        nd = len(self.problem.peripherals)
        G = np.zeros((2, nd, self.rows, H))
        for i in range(H):
            for li in range(self.coef.shape[3]):
                col = i - (li - 1)
                if 0 <= col < H:
                    G[:, :, i * spd:(i + 1) * spd, col] = self.coef[:, :, :, li].transpose(2, 1, 0)
        return G[0], G[1]

    def energy_costs(self) -> tuple[np.ndarray, np.ndarray]:
        """Area (VA s) each decision adds over the horizon: (cu, cs), each (devices, H)."""
        Gu, Gs = self.dense()
        return Gu.sum(axis=1) * self.dt, Gs.sum(axis=1) * self.dt

    def normalisation(self) -> tuple[float, float]:
        """(n1, n2) of eq. (4): 1 / range of J1 and of J2 (paper, section V-B).

        J1 ranges from the machining area (every peripheral off) to that plus every peripheral
        on along the horizon; J2 from the highest machining peak to that plus every
        peripheral's switch-on peak at the same instant.
        """
        span1 = sum(d.steady_va for d in self.models.devices.values()) * self.steps * self.step_s
        span2 = sum(d.peak_va() for d in self.models.devices.values())
        return 1.0 / max(span1, 1e-9), 1.0 / max(span2, 1e-9)

    def simulate(self, est: BenchEstimate, u: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Predicted S at every row for relay plan ``u`` (devices x H, 0/1; ``u_prev`` the
        states before it), simulating each model sample by sample: independent of the
        Toeplitz blocks, for tests."""
        R, spd = self.rows, self.samples_per_step
        out = self.models.machining.predict(est.x_machining, est.sample, R) + est.disturbance_va
        for j, name in enumerate(self.problem.peripherals):
            device = self.models.devices[name]
            prev = float(u_prev[j])
            fine = np.repeat(np.asarray(u[j], float), spd)
            before = np.concatenate([[prev], fine[:-1]])
            starts = ((fine > 0.5) & (before < 0.5)).astype(float)
            x = np.asarray(est.x_devices[name], float).copy()
            m = device.model
            # row r is sample r + 1: advance once with the input of sample 0 first
            for r in range(R):
                uk = np.array([fine[r], starts[r]])
                x = m.A @ x + m.B @ uk
                nxt = np.array([fine[r + 1], starts[r + 1]]) if r + 1 < R else np.zeros(2)
                out[r] += m.C @ x + m.D @ nxt
        return out

