"""Candidate plans of the EEC's horizon made feasible: the previous plan, shifted, as the
starting point of the next solve.

:func:`feasible` tells whether a relay plan keeps the dwell (a running one included) and the
level bounds; :func:`repair` gives a peripheral that breaks them one more run, the cheapest
that fits.
"""

from __future__ import annotations

import numpy as np

from hil.controllers.bench.eec_costs import HorizonCosts


def feasible(horizon: HorizonCosts, u: np.ndarray, u_prev: np.ndarray,
             fixed_steps: np.ndarray, c_lo: np.ndarray, c_hi: np.ndarray) -> bool:
    """Whether relay plan ``u`` keeps the dwell (running one included) and the levels."""
    return all(_device_feasible(horizon, j, u[j], u_prev, fixed_steps, c_lo, c_hi)
               for j in range(horizon.nd))


def _device_feasible(horizon: HorizonCosts, j: int, uj: np.ndarray, u_prev: np.ndarray,
                     fixed_steps: np.ndarray, c_lo: np.ndarray, c_hi: np.ndarray) -> bool:
    changes = np.nonzero(np.diff(np.concatenate([[u_prev[j]], uj])))[0]
    if changes.size and changes[0] < min(fixed_steps[j], horizon.H):
        return False
    if np.any(np.diff(changes) < horizon.dwell_steps[j]):
        return False
    c = np.cumsum(uj)
    return bool(np.all(c >= c_lo[j] - 1e-9) and np.all(c <= c_hi[j] + 1e-9))


def repair(horizon: HorizonCosts, u: np.ndarray, u_prev: np.ndarray, fixed_steps: np.ndarray,
           c_lo: np.ndarray, c_hi: np.ndarray, table: np.ndarray | None = None
           ) -> np.ndarray | None:
    """The candidate plan made feasible, or None.

    A peripheral whose part breaks its dwell or levels (a plan shifted by one step
    usually lacks production in its new last step) gets one more run: every run of the
    minimum length and every run to the horizon end is tried, and the feasible one with
    the least cost (energy plus peak, ``table`` from :meth:`HorizonCosts.peak_table`) is
    kept; without a table, the shortest final run.
    """
    u = u.copy()
    H = horizon.H
    for j in range(horizon.nd):
        if _device_feasible(horizon, j, u[j], u_prev, fixed_steps, c_lo, c_hi):
            continue
        candidates = []
        for a in range(H - 1, -1, -1):
            for end in {H, min(H, a + horizon.dwell_steps[j])}:
                trial = u[j].copy()
                trial[a:end] = 1.0
                if _device_feasible(horizon, j, trial, u_prev, fixed_steps, c_lo, c_hi):
                    candidates.append(trial)
            if candidates and table is None:
                break
        if not candidates:
            return None
        u[j] = candidates[int(np.argmin(horizon.costs(u, j, np.array(candidates), u_prev,
                                                      table)))] if table is not None \
            else candidates[0]
    return u
