"""The built-in servo controllers, built the way a user's are: registered in the entry-point
group ``hil.controllers`` (``mpc``, ``empc``, ``pid``) as factories
``(reference, params, context)``.

Params (default: ``hil servo run``'s flags): ``ht``, ``hu``, ``hp`` (horizons), ``ert``
(``foh`` | ``zoh``) for the MPCs, and ``umax`` [mA] for all three.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from controllers.servo.pid import CascadedPid, PidConfig
from controllers.servo.references import Reference
from hil.core.config import Table

if TYPE_CHECKING:  # the MPCs are imported when built: they bring scipy, daqp and HiGHS
    from controllers.servo.empc import ExplicitMpc
    from controllers.servo.mpc import MpcConfig, TrajectoryMpc


@dataclass(frozen=True)
class ServoContext:
    """What a run gives a controller factory that takes a ``context`` argument: the run's
    flags (horizons, current limit) and the session, whose ``topic(name, json_schema)`` and
    ``event(kind, message, **data)`` record a controller's own signals."""

    ht: int
    hu: int
    hp: int
    ert: str
    umax: float
    session: Any


def _params(params: Mapping[str, Any], name: str) -> Table:
    return Table(params, f"controller {name!r} params")


def mpc(reference: Reference, params: Mapping[str, Any], context: ServoContext
        ) -> TrajectoryMpc:
    """The trajectory-tracking MPC (online QP)."""
    from controllers.servo.mpc import TrajectoryMpc

    return TrajectoryMpc(reference, mpc_config(params, context, "mpc"))


def empc(reference: Reference, params: Mapping[str, Any], context: ServoContext
         ) -> ExplicitMpc:
    """The explicit MPC (regions searched through a binary tree)."""
    from controllers.servo.empc import ExplicitMpc

    return ExplicitMpc(reference, mpc_config(params, context, "empc"))


def pid(reference: Reference, params: Mapping[str, Any], context: ServoContext
        ) -> CascadedPid:
    """The cascaded P/PI + notch baseline."""
    table = _params(params, "pid")
    umax = table.number("umax", context.umax, above=0)
    table.done()
    return CascadedPid(reference, PidConfig(u_max=umax))


def mpc_config(params: Mapping[str, Any], context: ServoContext, name: str) -> MpcConfig:
    """The MPC's settings: the run's flags with ``params`` laid over them."""
    from controllers.servo.mpc import MpcConfig

    table = _params(params, name)
    umax = table.number("umax", context.umax, above=0)
    config = MpcConfig(ht=table.integer("ht", context.ht, at_least=1),
                       hu=table.integer("hu", context.hu, at_least=1),
                       hp=table.integer("hp", context.hp, at_least=1),
                       ert=table.string("ert", context.ert, choices=("foh", "zoh")),
                       u_min=-umax, u_max=umax)
    table.done()
    return config
