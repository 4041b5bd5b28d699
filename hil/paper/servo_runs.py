"""The lockstep sessions of the servo paper's reproduction: each one a ``hil servo run`` on the
emulated drive through the CiA 402 link (:func:`hil.servo.run.run_servo`), recorded to MCAP in
the report's sessions folder, its KPIs kept for the tables.

The explicit MPC runs as the built-in ``empc`` does, its law built once for all its runs, and
records the controller (eq. 15's affine law) of every tick on ``/empc/controller``: Fig. 16's
bottom graph, and the "never leaves region 1" of Fig. 14.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil.paper.servo_conditions import ServoConditions
from hil.servo.config import drive_for

if TYPE_CHECKING:
    from hil.controllers.servo.empc import ExplicitLaw, ExplicitMpc
    from hil.controllers.servo.references import Reference
    from hil.servo.builtin import ServoContext

CONTROLLER_TOPIC = "/empc/controller"
CONTROLLER_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.EmpcController",
    "description": "The explicit MPC's controller of the tick (eq. 15's M_i, m_i), numbered "
                   "as the paper does: 1 is the unconstrained law; 0: outside the parameter "
                   "box or in no region, solved online.",
    "properties": {"t_s": {"type": "number"},
                   "controller": {"type": "integer", "x-cdr": "int32"}},
}


@dataclass(frozen=True)
class Run:
    """One session: ``controller`` (a built-in's name, or a factory) on ``reference``."""

    name: str
    what: str
    controller: str | Callable[..., Any]
    reference: str
    duration_s: float
    limit_ma: float
    settle_s: float = 0.0
    ert: str = "foh"
    ht: int = 8
    params: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Session:
    """A finished session: its KPIs (``hil servo run --json``'s) and file."""

    run: Run
    kpis: dict[str, Any]

    @property
    def mcap(self) -> str:
        return str(self.kpis["mcap"])

    def __getitem__(self, key: str) -> Any:
        return self.kpis[key]


class SessionRunner:
    """Runs :class:`Run` s into ``folder`` one after the other (a name already run is not run
    again), a line of progress each through ``echo``."""

    def __init__(self, folder: Path, conditions: ServoConditions, planned: int,
                 echo: Callable[[str], None]) -> None:
        self.folder = folder
        self.conditions = conditions
        self.planned = planned
        self.echo = echo
        self.sessions: dict[str, Session] = {}
        self.wall_s = 0.0

    def __call__(self, run: Run) -> Session:
        from hil.servo.run import ServoRunOptions, run_servo

        done = self.sessions.get(run.name)
        if done is not None:
            return done
        c = self.conditions
        overrides = drive_for(run.limit_ma)
        overrides["master"]["cycle_period_us"] = c.cycle_period_us
        options = ServoRunOptions(
            controller=run.controller, params=dict(run.params), ert=run.ert, ht=run.ht,
            hu=run.ht, hp=c.hp, reference=run.reference, duration_s=run.duration_s,
            settle_s=run.settle_s, out=str(self.folder / f"{run.name}.mcap"), quiet=True,
            drive_overrides=overrides)
        start = time.perf_counter()
        kpis = run_servo(options).kpis
        wall = time.perf_counter() - start
        self.wall_s += wall
        session = self.sessions[run.name] = Session(run, kpis)
        self.echo(f"[{len(self.sessions)}/{self.planned}] {run.what}: max error "
                  f"{kpis['max_error_deg']:.4f} deg ({wall:.1f} s)")
        return session


def mpc_params(c: ServoConditions, **more: Any) -> dict[str, Any]:
    """The MPC's weights as the paper states them (Q, R), ``more`` laid over them."""
    return {"q": c.q, "r": c.r, **more}


def recorded_empc(law: ExplicitLaw) -> Callable[..., ExplicitMpc]:
    """A controller factory ``(reference, params, context)``: the built-in explicit MPC on
    ``law`` (built once), recording its controller of every tick on ``/empc/controller``."""
    from hil.controllers.servo.empc import ExplicitMpc
    from hil.servo.builtin import mpc_config

    class RecordedExplicitMpc(ExplicitMpc):
        """:class:`ExplicitMpc` whose every step records the controller it used."""

        def __init__(self, reference: Reference, context: ServoContext,
                     params: Mapping[str, Any]) -> None:
            super().__init__(reference, mpc_config(params, context, "empc"), law=law)
            self._clock = context.session.clock
            self._topic = context.session.topic(CONTROLLER_TOPIC, CONTROLLER_SCHEMA,
                                                high_rate=True)

        def step(self, position_deg: float, t_s: float) -> float:
            u = super().step(position_deg, t_s)
            index = self.explicit.last_controller if self.explicit.last_path == "explicit" \
                else -1
            self._topic.log(self._clock.time_ns(), (t_s, index + 1))
            return u

    def empc(reference: Reference, params: Mapping[str, Any],
             context: ServoContext) -> RecordedExplicitMpc:
        return RecordedExplicitMpc(reference, context, params)

    return empc
