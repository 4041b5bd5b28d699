"""Figs. 9-10 with viscous friction: the paper explains ZOH-ERT's predicted current ending near
zero by the friction of its plant model, which the printed model lost in rounding (its two
real poles sit at z = 1). This puts it back and measures the waterfall again.

The printed model's states are the motor and load speeds (x1, x2) and angles (x3, x4): the
rows of x1 and x2 sum to one over the speeds, a rigid body. :func:`viscous` makes both speeds
decay with time constant tau (friction to ground, a constant current then ends in a constant
speed). The builtin MPC always predicts with the printed model, so this is an offline
closed loop (:func:`hil.controllers.servo.sim.simulate`), plant and prediction model both
given the friction.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from hil.controllers.servo.model import StateSpaceModel, published_axis_model
from hil.controllers.servo.mpc import MpcConfig, TrajectoryMpc
from hil.controllers.servo.references import Sine
from hil.controllers.servo.sim import simulate
from hil.paper.servo_conditions import ServoConditions


def viscous(model: StateSpaceModel, tau_s: float) -> StateSpaceModel:
    """``model`` with both speeds decaying by T / tau per tick (viscous friction)."""
    A = model.A.copy()
    A[:2, :2] *= 1.0 - model.dt / tau_s
    return replace(model, A=A)


def prediction_ends(c: ServoConditions, ert: str, model: StateSpaceModel) -> dict[str, float]:
    """The waterfall metrics of :func:`hil.paper.servo.prediction_match`, offline on
    ``model``: the 10 Hz sine at the rated current, H_t = H_u = ``waterfall_ht``."""
    hu = c.waterfall_ht
    predicted: list[np.ndarray] = []

    class Recording(TrajectoryMpc):
        def step(self, position_deg: float, t_s: float) -> float:
            u = super().step(position_deg, t_s)
            predicted.append(self.prediction()[0][:hu].copy())
            return u

    reference = Sine(c.amplitude_deg, c.fast.frequency_hz)
    config = MpcConfig(ht=hu, hu=hu, hp=c.hp, ert=ert, q=c.q, r=c.r, u_min=-c.rated_ma,
                       u_max=c.rated_ma)
    run = simulate(Recording(reference, config, model=model), reference,
                   c.sine_duration_s(c.fast.frequency_hz), model=model,
                   current_limit_ma=c.rated_ma)
    ticks = np.flatnonzero(run.t >= c.settle_s - 1e-9)
    ticks = ticks[ticks + hu <= run.current.size]
    plans = np.array(predicted)[ticks]
    applied = np.stack([run.current[k:k + hu] for k in ticks])
    return {"end_ratio": float(np.mean(np.abs(plans[:, -1])) / np.mean(np.abs(applied[:, -1]))),
            "mismatch": float(np.sqrt(np.mean((plans - applied) ** 2)) /
                              np.sqrt(np.mean(applied ** 2)))}


def friction_sweep(c: ServoConditions) -> list[dict[str, Any]]:
    """ZOH's and FOH's waterfall metrics without friction and at each time constant."""
    base = published_axis_model()
    rows = []
    for tau in (None, *c.sweep_friction_tau_s):
        model = base if tau is None else viscous(base, tau)
        rows.append({"tau_s": tau, **{ert: prediction_ends(c, ert, model)
                                      for ert in ("zoh", "foh")}})
    return rows
