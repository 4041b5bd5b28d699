"""The built-in servo controllers, built the way a user's are: registered in the entry-point
group ``hil.controllers`` (``mpc``, ``empc``, ``pid``, ``setpoint``) as factories
``(reference, params, context)``. The first three return currents (CST); ``setpoint`` sends
the reference itself to a drive that closes its own loop: positions in CSP, velocities in CSV
and PV (:mod:`hil.controllers.servo.setpoint`), at any cycle period.

Params (default: ``hil servo run``'s flags): ``ht``, ``hu``, ``hp`` (horizons), ``ert``
(``foh`` | ``zoh``) for the MPCs, ``ti_us`` (the velocity PI's integral time, Table I's
2000 us) and ``vff`` (velocity feed-forward, the share of the reference's velocity added to the
velocity set-point: 0 to 1, default 0 as Table I) for the PID, and ``umax`` [mA] for all three.

Cycle periods (:func:`hil.controllers.base.runs_at`): the PID and the MPC run at every multiple of
500 us up to 10 ms (their model is the published axis stepped that many times; the PID refuses
a period at which its loop is unstable, naming a ``ti_us`` that holds it); the explicit MPC at
500 us only (its regions are built offline for it).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

from hil.controllers.base import CURRENT, POSITION, VELOCITY, returns, runs_at
from hil.controllers.servo.model import MODEL_PERIODS_US, SAMPLE_PERIOD_S, axis_model
from hil.controllers.servo.pid import GAINS, CascadedPid, PidConfig, check_stable, gain_of
from hil.controllers.servo.references import Reference
from hil.controllers.servo.setpoint import SetPointFollower
from hil.core.config import Table

if TYPE_CHECKING:  # the MPCs are imported when built: they bring scipy, daqp and HiGHS
    from hil.controllers.servo.empc import ExplicitMpc
    from hil.controllers.servo.mpc import MpcConfig, TrajectoryMpc


@dataclass(frozen=True)
class ServoContext:
    """What a run gives a controller factory that takes a ``context`` argument: the run's
    flags (horizons, current limit), the session, whose ``topic(name, json_schema)`` and
    ``event(kind, message, **data)`` record a controller's own signals, the cycle period
    its ``step`` is called at [s] and what it is to return (``output``: what the drive's mode
    takes, :class:`~hil.controllers.base.Output`)."""

    ht: int
    hu: int
    hp: int
    ert: str
    umax: float
    session: Any
    period_s: float = SAMPLE_PERIOD_S
    output: str = CURRENT


def _params(params: Mapping[str, Any], name: str) -> Table:
    return Table(params, f"controller {name!r} params")


@runs_at(MODEL_PERIODS_US)
def mpc(reference: Reference, params: Mapping[str, Any], context: ServoContext
        ) -> TrajectoryMpc:
    """The trajectory-tracking MPC (online QP), its prediction model at the run's period."""
    from hil.controllers.servo.mpc import TrajectoryMpc

    return TrajectoryMpc(reference, mpc_config(params, context, "mpc"),
                         axis_model(context.period_s))


@runs_at((500,))
def empc(reference: Reference, params: Mapping[str, Any], context: ServoContext
         ) -> ExplicitMpc:
    """The explicit MPC (regions searched through a binary tree)."""
    from hil.controllers.servo.empc import ExplicitMpc

    return ExplicitMpc(reference, mpc_config(params, context, "empc"))


@runs_at(MODEL_PERIODS_US)
def pid(reference: Reference, params: Mapping[str, Any], context: ServoContext
        ) -> CascadedPid:
    """The cascaded P/PI + notch baseline, discretised at the run's period (refused where its
    loop would be unstable)."""
    table = _params(params, "pid")
    umax = table.number("umax", context.umax, above=0)
    # the names, units and ranges of its tunables (controller.kp... while it runs)
    ti_us, kp, kv = (table.number(name, gain_of(PidConfig(), name), at_least=GAINS[name][1],
                                  at_most=GAINS[name][2]) for name in ("ti_us", "kp", "kv"))
    notch_hz = table.number("notch_hz", None, above=0, at_most=0.5 / context.period_s)
    notch_q = table.number("notch_q", PidConfig.notch_quality, above=0)
    vff = table.number("vff", PidConfig.velocity_feedforward, at_least=0, at_most=1)
    table.done()
    config = PidConfig(u_max=umax, ti_s=ti_us / 1e6, k_pos_rpm_per_deg=kp,
                       k_vel_a_per_rpm=kv, notch_hz=notch_hz, notch_quality=notch_q,
                       velocity_feedforward=vff)
    model = axis_model(context.period_s)
    check_stable(config, model)
    return CascadedPid(reference, config, model)


@returns(POSITION, VELOCITY)
@runs_at(range(1, 1_000_001))
def setpoint(reference: Reference, params: Mapping[str, Any], context: ServoContext
             ) -> SetPointFollower:
    """The reference itself as the set point of a drive that closes its loop: where it is one
    period ahead (CSP), or the velocity that takes the axis there (CSV, PV). No parameters."""
    _params(params, "setpoint").done()
    return SetPointFollower(reference, context.output, context.period_s)


def mpc_config(params: Mapping[str, Any], context: ServoContext, name: str) -> MpcConfig:
    """The MPC's settings: the run's flags with ``params`` laid over them."""
    from hil.controllers.servo.mpc import MpcConfig

    table = _params(params, name)
    umax = table.number("umax", context.umax, above=0)
    config = MpcConfig(ht=table.integer("ht", context.ht, at_least=1),
                       hu=table.integer("hu", context.hu, at_least=1),
                       hp=table.integer("hp", context.hp, at_least=1),
                       ert=table.string("ert", context.ert, choices=("foh", "zoh")),
                       q=table.number("q", float(cast(float, MpcConfig.q)), above=0),
                       r=table.number("r", float(cast(float, MpcConfig.r)), above=0),
                       u_min=-umax, u_max=umax)
    table.done()
    return config
