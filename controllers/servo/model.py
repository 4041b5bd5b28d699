"""The headstock axis model published in the servo paper (section III-A).

Discrete time, T = 500 us; input: q-axis motor current [mA]; output: motor position [deg].
The printed A_p has a double pole at z = 1 (rigid body, no friction after rounding) and a
lightly damped mode near 440 Hz. This is the nominal model the controllers are designed on and
the emulator's default plant; a different axis is a different instance, not an edit here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SAMPLE_PERIOD_S = 500e-6


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
