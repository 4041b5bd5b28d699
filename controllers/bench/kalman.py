"""Kalman filter of the bench's total apparent power (energy paper, eq. 9).

The extended model stacks the machining model and every peripheral's model (block diagonal
A, B, C), so one measured output, the total S, drives one estimate of every load's state.
Beyond the paper it carries a disturbance state ``d``: a random walk added to the output,
for whatever the models do not explain (an unknown load, a model error). Its estimate is the
"measured minus modelled" offset of the paper's section V-E, and it is what makes feedback
matter in the EEC: predictions shift by ``d`` and the plan moves against the contracted power
limit.

Timing: the reading of sample ``k`` reflects the relays latched during the step from ``k - 1``
to ``k``: :meth:`BenchKalman.advance` with those relay states, then
:meth:`BenchKalman.correct` with the reading. Feedthrough (``D``) is ignored: a meter reading
never depends on a relay written after it (identified bench models have ``D = 0``).

:class:`BenchKalman` is a :class:`~hil.controllers.base.BenchEstimator`: :meth:`~BenchKalman.update`
does both steps from a :class:`~hil.controllers.base.BenchSample`, and
:meth:`~BenchKalman.estimate` is what the EEC predicts from.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hil.controllers.base import BenchSample
from hil.controllers.bench.prediction import BenchEstimate, BenchModels


@dataclass(frozen=True)
class KalmanSettings:
    """Noise levels (``[kalman]`` of ``hil/configs/eec.toml``)."""

    model_sigma: float = 0.01        # process noise per model state and sample
    disturbance_sigma: float = 0.3   # random walk of d per sample [VA]
    meter_sigma: float = 1.5         # meter noise [VA]


class BenchKalman:
    """filterpy Kalman filter on the extended bench model plus a disturbance state."""

    def __init__(self, models: BenchModels, settings: KalmanSettings | None = None) -> None:
        settings = settings or KalmanSettings()
        self.models = models
        self.names = list(models.devices)
        mm = models.machining.model
        parts = [mm, *(models.devices[n].model for n in self.names)]
        self.sizes = [p.order for p in parts]
        n_x = sum(self.sizes) + 1
        n_u = sum(len(p.inputs) for p in parts)
        # imported here: filterpy imports scipy.stats, a second or more of every process
        # start that builds no estimator (the baseline controller, emulators, reports)
        from filterpy.kalman import KalmanFilter
        from scipy.linalg import block_diag

        kf = KalmanFilter(dim_x=n_x, dim_z=1, dim_u=n_u)
        kf.F = block_diag(*[p.A for p in parts], np.eye(1))
        kf.B = np.vstack([block_diag(*[p.B for p in parts]), np.zeros((1, n_u))])
        kf.H = np.concatenate([*[p.C for p in parts], [1.0]])[None, :]
        kf.Q = np.diag([settings.model_sigma ** 2] * (n_x - 1) + [settings.disturbance_sigma ** 2])
        kf.R = np.array([[settings.meter_sigma ** 2]])
        kf.x = np.zeros(n_x)
        kf.P = np.diag([1.0] * (n_x - 1) + [100.0])
        self.kf = kf
        self.rest = mm.rest_output
        self._machining_prev = np.zeros(len(models.machining.sequence.relays))
        self._device_prev = {n: False for n in self.names}
        self.sample = 0
        self.innovation = 0.0
        self._started = False  # the first sample has no step before it

    def inputs(self, machining: Mapping[str, bool], devices: Mapping[str, bool]) -> np.ndarray:
        """The extended input vector for relay states held over one sample (and remember
        them, so switch-on events are known)."""
        relays = self.models.machining.sequence.relays
        now = np.array([[1.0 if machining.get(r, False) else 0.0 for r in relays]])
        u_m = self.models.machining.inputs_at(now, self._machining_prev[None, :])[0]
        self._machining_prev = now[0]
        out = [u_m]
        for name in self.names:
            on = bool(devices.get(name, False))
            out.append(np.array([1.0 if on else 0.0,
                                 1.0 if on and not self._device_prev[name] else 0.0]))
            self._device_prev[name] = on
        return np.concatenate(out)

    def advance(self, machining: Mapping[str, bool], devices: Mapping[str, bool]) -> None:
        """Predict one sample ahead with the relay states held during it."""
        self.kf.predict(u=self.inputs(machining, devices))
        self.sample += 1

    def correct(self, s_measured: float) -> None:
        """Correct with the reading of the current sample."""
        z = s_measured - self.rest  # the models are strictly proper or D is ~0 (see module)
        self.kf.update(np.array([z]))
        self.innovation = float(np.ravel(self.kf.y)[0])

    def update(self, sample: BenchSample) -> None:
        """One sample: advance with the relays held since the previous one (not before the
        first), then correct with the reading (not when the poll failed)."""
        if self._started:
            self.advance(sample.relays, sample.relays)
        self._started = True
        if sample.power_va is not None:
            self.correct(sample.power_va)

    @property
    def disturbance_va(self) -> float:
        return float(self.kf.x[-1])

    @property
    def output_va(self) -> float:
        """Estimated total S at the latest sample."""
        return float((self.kf.H @ self.kf.x).item()) + self.rest

    def estimate(self) -> BenchEstimate:
        """The states the EEC's prediction starts from (``sample``: samples since start)."""
        x = self.kf.x
        cuts = np.cumsum([0, *self.sizes])
        devices = {name: x[cuts[k + 1]:cuts[k + 2]].copy() for k, name in enumerate(self.names)}
        return BenchEstimate(self.sample, x[:cuts[1]].copy(), devices, float(x[-1]),
                             self.output_va, self.innovation)
