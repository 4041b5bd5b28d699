"""What an identified discrete model says about the machine: its resonances, its integrators and
its gain at low frequency.

* **Resonances** - each complex pole pair z, z* of A, read in continuous time as s = ln(z) / dt:
  natural frequency |s| / 2 pi [Hz] and damping ratio -Re(s) / |s|. ``peak_gain`` is the
  mode's own peak, |r| / (1 - |z|) with r its residue (the largest entry of C v w^H B): a mode
  the data really hold stands out; one fitted to noise has a small peak.
* **Integrators** - poles slower than the record can tell from an integrator: |s| < 1 / the
  record's length (their time constant is longer than the record; an ideal integrator sits at
  z = 1, an identified one a hair off it).
* **Gain** - without integrators, the DC gain C (I - A)^-1 B + D (output units per input
  unit). With k integrators the DC gain is infinite (``dc_gain`` None): what is meaningful is
  the gain of the integrating part, lim s^k G(s) (output units / s^k per input unit): for a
  servo axis, current -> position with k = 2, the rigid-body gain in deg/s^2 per mA
  (acceleration per current, i.e. torque constant over inertia). It is computed on the integrator
  cluster alone (split from the other modes by an ordered Schur form and a Sylvester equation),
  taken to continuous time (matrix logarithm, zero-order-hold input), as C1 A1^(k-1) B1 there.

Pure numpy/scipy, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg


@dataclass(frozen=True)
class Resonance:
    """One complex pole pair, in continuous time."""

    frequency_hz: float
    damping_ratio: float
    peak_gain: float


@dataclass(frozen=True)
class ModelAnalysis:
    """Resonances (by frequency), the number of integrators and the gain that is meaningful:
    ``dc_gain`` without integrators, ``integrator_gain`` (lim s^k G(s)) with k of them; both
    outputs x inputs."""

    resonances: tuple[Resonance, ...]
    integrators: int
    dc_gain: np.ndarray | None
    integrator_gain: np.ndarray | None
    slowest_hz: float      # poles slower than this count as integrators

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (``hil identify --json``'s ``analysis``)."""
        return {
            "resonances": [{"frequency_hz": r.frequency_hz, "damping_ratio": r.damping_ratio,
                            "peak_gain": r.peak_gain} for r in self.resonances],
            "integrators": self.integrators,
            "dc_gain": None if self.dc_gain is None else self.dc_gain.tolist(),
            "integrator_gain": None if self.integrator_gain is None
            else self.integrator_gain.tolist(),
            "integrator_below_hz": self.slowest_hz,
        }


def analyse(A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, dt: float,
            record_s: float) -> ModelAnalysis:
    """The analysis of x(k+1) = A x + B u, y = C x + D u sampled every ``dt`` [s], identified
    from a record ``record_s`` [s] long (which poles count as integrators)."""
    slowest = 1.0 / record_s            # rad/s
    poles = np.linalg.eigvals(A).astype(complex)
    with np.errstate(divide="ignore", invalid="ignore"):  # z = 0 (a delay): infinitely fast
        s = np.log(poles) / dt
    slow = np.abs(s) < slowest
    k = int(slow.sum())
    resonances = tuple(sorted(
        (_resonance(A, B, C, z, si) for z, si, is_slow in zip(poles, s, slow, strict=True)
         if z.imag > 0 and not is_slow),
        key=lambda r: r.frequency_hz))
    if k == 0:
        dc = C @ np.linalg.solve(np.eye(A.shape[0]) - A, B) + D
        return ModelAnalysis(resonances, 0, dc, None, slowest / (2 * math.pi))
    return ModelAnalysis(resonances, k, None, _integrator_gain(A, B, C, dt, slowest, k),
                         slowest / (2 * math.pi))


def _resonance(A: np.ndarray, B: np.ndarray, C: np.ndarray, z: complex, s: complex
               ) -> Resonance:
    w, vl, vr = scipy.linalg.eig(A, left=True, right=True)
    i = int(np.argmin(np.abs(w - z)))
    v, u = vr[:, i], vl[:, i].conj()
    residue = np.outer(C @ v, u @ B) / (u @ v)
    peak = float(np.max(np.abs(residue))) / max(1.0 - abs(z), 1e-300)
    return Resonance(float(abs(s) / (2 * math.pi)), float(-s.real / abs(s)), peak)


def _integrator_gain(A: np.ndarray, B: np.ndarray, C: np.ndarray, dt: float, slowest: float,
                     k: int) -> np.ndarray:
    """lim s^k G(s) of the integrator cluster (the k poles with |ln z| / dt < ``slowest``)."""
    def in_cluster(re: float, im: float) -> bool:
        return bool(abs(complex(re, im)) > 0 and abs(np.log(complex(re, im))) / dt < slowest)

    T, Z, sdim = scipy.linalg.schur(A, output="real", sort=in_cluster)
    T11, T12, T22 = T[:sdim, :sdim], T[:sdim, sdim:], T[sdim:, sdim:]
    X = scipy.linalg.solve_sylvester(T11, -T22, -T12) if T22.size else \
        np.zeros((sdim, 0))
    Bt = Z.T @ B
    B1 = Bt[:sdim] - X @ Bt[sdim:]
    C1 = (C @ Z)[:, :sdim]
    Ac = np.real(scipy.linalg.logm(T11)) / dt
    # zero-order hold: B1 = (integral of e^(Ac t) over one period) Bc
    block = np.zeros((2 * sdim, 2 * sdim))
    block[:sdim, :sdim], block[:sdim, sdim:] = Ac * dt, np.eye(sdim) * dt
    hold = scipy.linalg.expm(block)[:sdim, sdim:]
    Bc = np.linalg.solve(hold, B1)
    return np.asarray(C1 @ np.linalg.matrix_power(Ac, k - 1) @ Bc)
