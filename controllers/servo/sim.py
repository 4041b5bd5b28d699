"""Offline closed-loop simulation of a servo controller on the published axis model.

Pure numpy, no clocks or I/O: the plant x(k+1) = A_p x(k) + B_p (sat(u(k)) + d(k)) is
advanced tick by tick; the controller sees the measured position wrapped to [0, 360) (as the
drive reports it) and returns the current command, which the drive clips to its limit. Used by
the tests, the Figs. 7-8 table (:func:`figure_table`) and the benchmarks.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil.controllers.base import Resettable, ServoController
from hil.controllers.servo.model import StateSpaceModel, published_axis_model
from hil.controllers.servo.mpc import MpcConfig, TrajectoryMpc
from hil.controllers.servo.pid import CascadedPid, PidConfig
from hil.controllers.servo.references import Disturbance, Reference, Sine


@dataclass
class SimResult:
    """Per-tick arrays of one run; ``error`` is position - reference wrapped to ±180 deg."""

    t: np.ndarray
    reference: np.ndarray
    position: np.ndarray
    current: np.ndarray
    compute_ns: np.ndarray
    wall_s: float

    @property
    def error(self) -> np.ndarray:
        return (self.position - self.reference + 180.0) % 360.0 - 180.0

    def window(self, start_s: float = 0.0, end_s: float = math.inf) -> np.ndarray:
        """Boolean mask of the ticks with start_s <= t < end_s."""
        return (self.t >= start_s - 1e-12) & (self.t < end_s - 1e-12)

    def metrics(self, start_s: float = 0.0, end_s: float = math.inf) -> dict[str, float]:
        """max/RMS/cumulative |error| [deg] and peak |current| [mA] over a time window."""
        mask = self.window(start_s, end_s)
        err = np.abs(self.error[mask])
        return {
            "max_error_deg": float(err.max()),
            "rms_error_deg": float(np.sqrt(np.mean(err**2))),
            "cumulative_error_deg": float(err.sum()),
            "peak_current_mA": float(np.abs(self.current[mask]).max()),
        }


def rest_state(model: StateSpaceModel, position_deg: float) -> np.ndarray:
    """Plant state at rest at ``position_deg``: (A - I) x = 0, C x = position."""
    n = model.n_states
    lhs = np.vstack([model.A - np.eye(n), model.C])
    rhs = np.zeros(n + 1)
    rhs[-1] = position_deg
    return np.linalg.lstsq(lhs, rhs, rcond=None)[0]


def simulate(controller: ServoController, reference: Reference, duration_s: float,
             model: StateSpaceModel | None = None, current_limit_ma: float = 1000.0,
             disturbance: Disturbance | None = None, start_deg: float | None = None,
             wrap: bool = True) -> SimResult:
    """Run ``controller`` against the model for ``duration_s``; the axis starts at rest at
    ``start_deg`` (default: the reference at t = 0)."""
    model = model or published_axis_model()
    dt = model.dt
    ticks = round(duration_s / dt)
    t = np.arange(ticks) * dt
    ref = np.asarray(reference.position(t), dtype=float)
    x = rest_state(model, float(ref[0]) if start_deg is None else start_deg)
    A, B, C = model.A, model.B[:, 0], model.C[0]
    position = np.empty(ticks)
    current = np.empty(ticks)
    compute_ns = np.empty(ticks, dtype=np.int64)
    if isinstance(controller, Resettable):
        controller.reset()
    clock = time.perf_counter_ns
    wall0 = time.perf_counter()
    for k in range(ticks):
        y = float(C @ x)
        position[k] = y
        tk = float(t[k])
        t0 = clock()
        u = controller.step(y % 360.0 if wrap else y, tk)
        compute_ns[k] = clock() - t0
        u = min(max(u, -current_limit_ma), current_limit_ma)
        current[k] = u
        if disturbance is not None:
            u += disturbance(tk)
        x = A @ x + B * u
    return SimResult(t, ref, position, current, compute_ns, time.perf_counter() - wall0)


# -- Figs. 7-8: normalised cumulative tracking error vs trajectory horizon --------------------

WARMUP_S = 0.5  # settle before the measured cycle (covers the PID's slow integral transient)


def cycle_error(make: Callable[[Reference], ServoController], frequency: float,
                amplitude: float, current_limit_ma: float) -> dict[str, float]:
    """Metrics over one complete sine cycle after ``WARMUP_S`` (rounded up to whole cycles)."""
    period = 1.0 / frequency
    warmup = math.ceil(WARMUP_S / period - 1e-9) * period
    reference = Sine(amplitude, frequency)
    result = simulate(make(reference), reference, warmup + period,
                      current_limit_ma=current_limit_ma)
    return result.metrics(warmup, warmup + period)


PAPER_CASES = ((1.0, 1000.0), (10.0, 12000.0), (10.0, 1000.0))
"""(frequency [Hz], current limit [mA]): 1 Hz within the paper's 1000 mA, 10 Hz at the
motor's rated 12 A (2 deg at 10 Hz needs about 2.8 A), and 10 Hz at the printed 1000 mA where
tracking needs more current than allowed (the MPCs saturate)."""


def _case(frequency: float, limit: float, horizons: list[int], hp: int, q: float, r: float,
          amplitude: float) -> dict[str, Any]:
    """One panel of Figs. 7-8 (see :func:`figure_table`)."""

    def mpc(ert: str, ht: int) -> dict[str, float]:
        cfg = MpcConfig(ht=ht, hu=ht, hp=hp, ert=ert, q=q, r=r, u_min=-limit, u_max=limit)
        return cycle_error(lambda ref: TrajectoryMpc(ref, cfg), frequency, amplitude, limit)

    def pid(vff: bool) -> dict[str, float]:
        cfg = PidConfig(u_max=limit, velocity_feedforward=vff)
        return cycle_error(lambda ref: CascadedPid(ref, cfg), frequency, amplitude, limit)

    setpoint = mpc("zoh", 1)
    pid_plain, pid_vff = pid(False), pid(True)
    zoh = [setpoint if ht == 1 else mpc("zoh", ht) for ht in horizons]
    foh = [mpc("foh", ht) if ht >= 2 else None for ht in horizons]
    base = setpoint["cumulative_error_deg"]

    def normalised(metrics: dict[str, float] | None) -> float | None:
        return None if metrics is None else metrics["cumulative_error_deg"] / base

    return {
        "frequency_hz": frequency,
        "current_limit_mA": limit,
        "horizons": horizons,
        "setpoint": setpoint,
        "pid": normalised(pid_plain),
        "pid_vff": normalised(pid_vff),
        "zoh": [normalised(m) for m in zoh],
        "foh": [normalised(m) for m in foh],
        "absolute": {"pid": pid_plain, "pid_vff": pid_vff, "zoh": zoh, "foh": foh},
    }


def figure_table(cases: Iterable[tuple[float, float]] = PAPER_CASES,
                 horizons: Iterable[int] = range(1, 9), hp: int = 50, q: float = 1e6,
                 r: float = 1.0, amplitude: float = 2.0) -> list[dict[str, Any]]:
    """Figs. 7-8: per (frequency, current limit) case, the cumulative |error| over one cycle
    for PID and for MPC with ZOH and FOH ERT at H_t = H_u = each horizon, normalised to MPC
    set-point tracking (ZOH, H_t = 1), as in the paper; FOH is undefined at H_t = 1 (None).
    ``pid_vff`` is the same PID with velocity feed-forward, which Table I does not have.
    ``absolute`` holds the un-normalised metrics of every run."""
    horizons = list(horizons)
    return [_case(f, limit, horizons, hp, q, r, amplitude) for f, limit in cases]
