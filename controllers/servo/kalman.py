"""Steady-state Kalman filter for the servo axis: estimates the unmeasured states from position.

Design choice (disturbance handling): the filter runs on the MPC's velocity-form model
(eq. 4-5), state x = [Δx_p; y], input Δu. A constant (or slowly varying) torque disturbance d
on the plant input becomes Δd in that model, which is zero except at the instants d changes, so
the model stays exact under constant disturbances without an extra disturbance state: the
estimate of Δx_p returns to zero at any equilibrium and the MPC's integral action (it decides
Δu, not u) removes the offset. The process noise is therefore modelled as steps of an input
disturbance, w = B Δd with std(Δd) = ``disturbance_step_ma`` per tick, plus a tiny white noise
on every state to keep the Riccati equation regular; the position measurement has std
``measurement_deg``. Only the ratio of the two matters for the gain.

filterpy's :class:`~filterpy.kalman.KalmanFilter` computes the gain: its predict/update
recursion is iterated until the gain stops changing (the stationary Riccati solution) and the
converged filter is kept in :attr:`SteadyStateKalman.filter`. The online step then uses the
fixed gain (two small matrix-vector products), because filterpy's per-tick covariance update
would cost most of the 500 us budget.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hil.controllers.errors import ControllerSetupError

if TYPE_CHECKING:
    from filterpy.kalman import KalmanFilter


@dataclass(frozen=True)
class KalmanTuning:
    """Noise levels the steady-state gain is computed from."""

    disturbance_step_ma: float = 100.0
    measurement_deg: float = 1e-3
    state_noise: float = 1e-9
    max_iterations: int = 100_000
    tolerance: float = 1e-12

    def __post_init__(self) -> None:
        for name in ("disturbance_step_ma", "measurement_deg", "state_noise", "tolerance"):
            if not getattr(self, name) > 0:
                raise ControllerSetupError(f"kalman.{name} must be > 0, got {getattr(self, name)}")


class SteadyStateKalman:
    """x̂(k|k) = x̂(k|k-1) + K (y(k) - C x̂(k|k-1)),  x̂(k+1|k) = A x̂(k|k) + B Δu(k)."""

    def __init__(self, A: np.ndarray, B: np.ndarray, C: np.ndarray,
                 tuning: KalmanTuning | None = None) -> None:
        self.tuning = tuning or KalmanTuning()
        self.A = np.asarray(A, dtype=float)
        self.B = np.asarray(B, dtype=float).reshape(-1)
        self.C = np.asarray(C, dtype=float).reshape(-1)
        n = self.A.shape[0]
        if self.A.shape != (n, n) or self.B.size != n or self.C.size != n:
            raise ControllerSetupError("kalman: A must be n x n, B n x 1 and C 1 x n")
        self.filter = self._converged_filter()
        self.gain = self.filter.K.reshape(-1).copy()
        self.x = np.zeros(n)
        self._prior = np.zeros(n)

    def _converged_filter(self) -> KalmanFilter:
        # imported here: filterpy imports scipy.stats, a second or more of every process
        # start that builds no MPC (PID runs, emulators, reports)
        from filterpy.kalman import KalmanFilter

        n = self.A.shape[0]
        t = self.tuning
        kf = KalmanFilter(dim_x=n, dim_z=1, dim_u=1)
        kf.F = self.A.copy()
        kf.B = self.B.reshape(n, 1).copy()
        kf.H = self.C.reshape(1, n).copy()
        kf.Q = t.disturbance_step_ma**2 * np.outer(self.B, self.B) + t.state_noise**2 * np.eye(n)
        kf.R = np.array([[t.measurement_deg**2]])
        kf.P = np.eye(n)
        previous = None
        zero = np.zeros((1, 1))
        for _ in range(t.max_iterations):
            kf.predict()
            kf.update(zero)
            if previous is not None:
                change = np.max(np.abs(kf.K - previous))
                if change <= t.tolerance * np.max(np.abs(kf.K)):
                    return kf
            previous = kf.K.copy()
        raise ControllerSetupError(
            f"kalman: gain did not converge in {t.max_iterations} iterations")

    def reset(self, x0: np.ndarray) -> None:
        """Start from the prior estimate ``x0`` (before the first measurement)."""
        self._prior = np.array(x0, dtype=float)
        self.x = self._prior.copy()

    def update(self, y: float, out: np.ndarray | None = None) -> np.ndarray:
        """Correct the prior with measurement ``y``; returns the posterior x̂(k|k) (a view),
        also written to ``out`` when given (the MPC's θ)."""
        prior = self._prior
        innovation = y - float(self.C @ prior)
        np.multiply(self.gain, innovation, out=self.x)
        self.x += prior
        if out is not None:
            out[:] = self.x
        return self.x

    def predict(self, du: float) -> None:
        """Propagate the posterior one tick with the applied input change ``du``."""
        prior = self._prior
        np.matmul(self.A, self.x, out=prior)
        prior += self.B * du

    def observer_poles(self) -> np.ndarray:
        """Eigenvalues of the estimation error dynamics A - A K C (all inside the unit circle)."""
        return np.linalg.eigvals(self.A - np.outer(self.A @ self.gain, self.C))
