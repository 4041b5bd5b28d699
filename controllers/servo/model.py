"""The headstock axis model published in the servo paper (section III-A).

Discrete time, T = 500 us; input: q-axis motor current [mA]; output: motor position [deg].
The printed A_p has a double pole at z = 1 (rigid body, no friction after rounding) and a
lightly damped mode near 440 Hz. This is the nominal model the controllers are designed on and
the emulator's default plant; a different axis is a different instance, not an edit here.

The paper publishes no continuous-time model, so another cycle period is a whole multiple N of
500 us (:data:`MODEL_PERIODS_US`): :func:`axis_model` steps the printed model N times with the
current held (A^N, (A^(N-1) + ... + A + I) B), exactly what the emulated drive does between two
SYNCs of that period - no continuous-time model is guessed from the rounded coefficients.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SAMPLE_PERIOD_S = 500e-6
#: the cycle periods the model is given at [us]: the multiples of its 500 us up to 10 ms
#: (100 Hz; the PID's velocity loop and the MPC's horizon are meant for a servo loop, not
#: slower)
MODEL_PERIODS_US = range(500, 10_001, 500)


@dataclass(frozen=True)
class StateSpaceModel:
    """x(k+1) = A x(k) + B u(k), y(k) = C x(k) + D u(k), sampled every ``dt`` seconds."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    dt: float

    @property
    def n_states(self) -> int:
        return self.A.shape[0]


def published_axis_model() -> StateSpaceModel:
    """A_p, B_p, C_p exactly as printed in the paper."""
    A = np.array([
        [3.6e-1, 6.4e-1, -2.1e3, 2.1e3],
        [1.8e-1, 8.2e-1, 5.9e2, -5.9e2],
        [3.8e-4, 1.2e-4, 3.7e-1, 6.3e-1],
        [3.3e-5, 4.7e-4, 1.8e-1, 8.2e-1],
    ])
    B = np.array([[8.6e-5], [7.5e-6], [2.5e-8], [9.9e-10]])
    C = np.array([[0.0, 0.0, 5.7e1, 0.0]])
    D = np.zeros((1, 1))
    return StateSpaceModel(A=A, B=B, C=C, D=D, dt=SAMPLE_PERIOD_S)


def resampled(model: StateSpaceModel, period_s: float) -> StateSpaceModel:
    """``model`` sampled every ``period_s``, a whole multiple N of its own period, the input
    held over the N steps: A^N and (A^(N-1) + ... + A + I) B (C and D unchanged)."""
    steps = round(period_s / model.dt)
    if steps < 1 or abs(steps * model.dt - period_s) > 1e-9 * period_s:
        raise ValueError(f"a period of {period_s * 1e6:g} us is no whole multiple of the "
                         f"model's {model.dt * 1e6:g} us")
    A, B = np.eye(model.n_states), np.zeros_like(model.B)
    for _ in range(steps):  # B_N = A B_(N-1) + B, A_N = A A_(N-1)
        A, B = model.A @ A, model.A @ B + model.B
    return StateSpaceModel(A=A, B=B, C=model.C, D=model.D, dt=steps * model.dt)


def axis_model(period_s: float = SAMPLE_PERIOD_S) -> StateSpaceModel:
    """The published axis at a cycle period of ``period_s`` (a multiple of 500 us): the
    printed model itself at 500 us."""
    model = published_axis_model()
    return model if period_s == SAMPLE_PERIOD_S else resampled(model, period_s)
