"""A bench controller in the loop: what it is told, when it decides, what is recorded.

* :class:`Observer` (every sample) - takes the reading (read), feeds the controller's
  estimator (:class:`~hil.controllers.base.BenchEstimator`, the EEC's Kalman filter) in the loop
  thread (compute) and adds the reading to the KPIs (record);
* :class:`ControllerTask` (every decision step) - takes a
  :class:`~hil.controllers.base.BenchObservation` at the decision instant, in the loop thread (the
  estimator's ``estimate()`` included), asks any :class:`~hil.controllers.base.BenchController`
  (compute), and sends its answer through the safety layer (write);
* :class:`GuardedController` - any controller as the loop calls it: timed, held to a budget,
  its answer checked; :class:`RecordedEEC` - the EEC, whose estimates, plans and fallbacks go
  to ``/eec/estimate``, ``/eec/plan`` and ``/events``;
* :class:`BenchContext` - what a controller factory may ask for besides its params.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from hil.bench.kpis import BenchKpis
from hil.contracts import EventSink
from hil.controllers.base import (
    BenchController,
    BenchEstimator,
    BenchObservation,
    BenchSample,
    TunableParam,
    estimator_of,
)
from hil.core.guard import guarded_call
from hil.core.loop import Task
from hil.core.realtime import ordinary_thread
from hil.core.stats import TimingHistogram
from hil.core.verdict import SignalWatch
from hil.errors import ControllerError

if TYPE_CHECKING:
    from hil.bench.config import EecConfig
    from hil.bench.rig import BenchRig
    from hil.controllers.bench.eec import EEC
    from hil.controllers.bench.problem import BenchProblem
    from hil.core.session import Session

PLAN_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "hil.EECPlan",
    "description": "One MILP solve of the EEC: the relay plan over the horizon (1 value per "
                   "step), the predicted levels and power, solver status and time",
    "properties": {
        "t_s": {"type": "number", "description": "decision time since the sequence start"},
        "status": {"type": "string", "description": "optimal, time_limit, ..."},
        "solve_ms": {"type": "number"},
        "gap": {"type": "number", "description": "relative gap to the bound (0: proven)"},
        "nodes": {"type": "integer",
                  "description": "MILP branch-and-bound nodes, or DP partial plans kept"},
        "bound": {"type": "number", "description": "proven lower bound of the objective"},
        "objective": {"type": "number"},
        "peak_va": {"type": "number", "description": "predicted highest total VA"},
        "energy_vas": {"type": "number", "description": "predicted area over the horizon"},
        "rows": {"type": "integer", "description": "J2 pattern rows after pruning"},
        "u": {"type": "object", "description": "relay plan per peripheral (0/1 per step)"},
        "q": {"type": "object", "description": "predicted level per resource (H+1 values)"},
        "power_va": {"type": "array", "items": {"type": "number"},
                     "description": "predicted highest total VA in each step"},
    },
}
ESTIMATE_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "hil.BenchEstimate",
    "description": "Kalman filter of the total VA at the decision instants",
    "properties": {"disturbance_va": {"type": "number"}, "output_va": {"type": "number"},
                   "innovation_va": {"type": "number"}},
}


@dataclass
class RunLog:
    """What the loop saw, reduced as it goes: the KPIs' running accumulators and histograms of
    the decision times (constant memory, whatever the length of the run)."""

    kpis: BenchKpis
    solve_ms: TimingHistogram = field(default_factory=TimingHistogram)  # the solver's (EEC)
    decide_ms: TimingHistogram = field(default_factory=TimingHistogram)  # every decide() call
    fallbacks: int = 0
    solver_limits: int = 0
    max_gap: float = 0.0          # largest relative gap of a solve (0: every one proven)
    solver_reports: bool = False  # solve_ms holds a solver's times (else decide_ms is used)


class Observer(Task):
    """Every sample: the reading as the sampler took it (read), the controller's estimator fed
    the relays held during the last step and this reading (compute), the reading added to the
    KPIs (record)."""

    def __init__(self, rig: BenchRig, log: RunLog, clock_origin: Callable[[], int],
                 estimator: BenchEstimator | None) -> None:
        super().__init__("estimator", 1)
        self.rig, self.log = rig, log
        self.estimator = estimator
        self._origin = clock_origin
        # relay samples of a lost link, held until it is restored (then counted at the safe
        # level the safety layer drove them to) or given up on (then dropped: the KPIs end
        # where the bench was last heard); at most give_up_s of samples
        self._held: list[float] = []
        self._may_give_up = rig.link.give_up_ns > 0
        # this sample: time, total VA (None: no new reading), relays, link up, new levels
        self._sample: tuple[float, float | None, dict[str, bool], bool, Any] | None = None

    def read(self, t_ns: int) -> None:
        sampler, bench = self.rig.sampler, self.rig.bench
        t = (t_ns - self._origin()) / 1e9
        power = sampler.fresh_power
        total_va = power["total_va"] if power is not None else None
        link_up = bench.link_up
        # the relays' real state is unknown while the link is lost: driven to their safe level
        relays = bench.relays() if link_up else dict(bench.safe_levels)
        self._sample = (t, total_va, relays, link_up, sampler.fresh_levels)

    def compute(self, t_ns: int) -> None:
        if self.estimator is not None and self._sample is not None:
            t, total_va, relays, _, _ = self._sample
            self.estimator.update(BenchSample(t, total_va, relays))

    def record(self, t_ns: int) -> None:
        if self._sample is None:
            return
        t, total_va, relays, link_up, levels = self._sample
        kpis = self.log.kpis
        if link_up:
            self._release_held()
            kpis.relays(t, relays)
        elif self._may_give_up:
            self._held.append(t)
        else:
            kpis.relays(t, relays)
        if total_va is not None:
            kpis.power(t, total_va)
        if levels is not None:
            kpis.levels(t, levels)

    def _release_held(self) -> None:
        safe = self.rig.bench.safe_levels
        for t in self._held:
            self.log.kpis.relays(t, safe)
        self._held.clear()

    def finish(self, gave_up: bool) -> None:
        """After the run: a loss the run gave up on is dropped, one it ended in is counted."""
        if gave_up:
            self._held.clear()
        self._release_held()


class ControllerTask(Task):
    """Once per decision step: an observation in, the peripherals' relays out through the
    safety layer.

    Lockstep: the decision is computed in the tick of the decision instant. Real time
    (``asynchronous``): the decision runs in a worker thread (HiGHS releases the GIL) so the
    loop keeps sampling at 100 Hz; its command is applied ``apply_delay_s`` after the
    decision instant, or when it is ready if later. The fixed delay keeps the spacing of
    the switches equal to the decision spacing, so the safety layer's dwell agrees with the
    controller's. A decision instant that finds the previous decision still running is
    skipped (counted in ``skipped``). The observation, the estimate included, is always taken
    in the loop thread at the decision instant.
    """

    def __init__(self, step_ticks: int, tick_ns: int, rig: BenchRig,
                 peripherals: tuple[str, ...], controller: BenchController,
                 origin: Callable[[], int], *, asynchronous: bool = False,
                 apply_delay_s: float = 0.1) -> None:
        super().__init__("controller", 1 if asynchronous else step_ticks)
        self._step_ns = step_ticks * tick_ns
        self.rig, self.peripherals, self.controller = rig, peripherals, controller
        self.estimator = estimator_of(controller)
        self._origin = origin
        self.asynchronous = asynchronous
        self.apply_delay_s = apply_delay_s
        self.skipped = 0
        self._last_step = -1
        self._pending: tuple[Future[Mapping[str, bool]], int] | None = None
        self._command: Mapping[str, bool] | None = None  # this tick's decision, to write
        # started from the (hardened) loop thread: its worker must not inherit FIFO and the core
        self._executor = (ThreadPoolExecutor(1, "eec", initializer=ordinary_thread)
                          if asynchronous else None)

    def _observe(self, t_ns: int) -> BenchObservation | None:
        levels = self.rig.sampler.latest_levels
        if levels is None or not self.rig.bench.link_up:
            return None  # nothing to decide on: the safety layer holds the relays
        relays = self.rig.bench.relays()
        power = self.rig.sampler.latest_power
        return BenchObservation(
            round((t_ns - self._origin()) / 1e9, 9), dict(levels),
            {n: relays[n] for n in self.peripherals},
            power["total_va"] if power is not None else math.nan,
            self.estimator.estimate() if self.estimator is not None else None)

    def compute(self, t_ns: int) -> None:
        """Lockstep: decide on this tick's observation. Real time: start a decision at a
        decision instant, and take one that is done and due."""
        self._command = None
        if not self.asynchronous:
            obs = self._observe(t_ns)
            if obs is not None:
                self._command = self.controller.decide(obs)
            return
        step = (t_ns - self._origin()) // self._step_ns
        if step > self._last_step:  # a decision instant (the first tick of a step)
            self._last_step = step
            if self._pending is not None:
                self.skipped += 1
            else:
                obs = self._observe(t_ns)
                if obs is not None and self._executor is not None:
                    due = t_ns + round(self.apply_delay_s * 1e9)
                    self._pending = (self._executor.submit(self.controller.decide, obs), due)
        if self._pending is not None and t_ns >= self._pending[1] and self._pending[0].done():
            future, _ = self._pending
            self._pending = None
            self._command = future.result()

    def write(self, t_ns: int) -> None:
        command = self._command
        if command:
            current = self.rig.bench.commanded()
            changes = {n: on for n, on in command.items() if current[n] != on}
            if changes:
                self.rig.bench.set_relays(changes, t_ns)

    def safe_state(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._pending = None


class RecordedEEC:
    """The EEC as a run uses it (a :class:`~hil.controllers.base.BenchController`): each decision
    records the estimate it started from (``/eec/estimate``), its plan (``/eec/plan``), its
    fallbacks and solver trouble (``/events``) and its solve time (KPIs)."""

    def __init__(self, eec: EEC, session: Session, problem: BenchProblem, log: RunLog,
                 origin: Callable[[], int]) -> None:
        self.eec, self.session, self.problem, self.log = eec, session, problem, log
        log.solver_reports = True
        self.estimator = eec.estimator
        self.origin = origin
        self.plan_topic = session.topic("/eec/plan", PLAN_SCHEMA)
        self.estimate_topic = session.topic("/eec/estimate", ESTIMATE_SCHEMA)

    def tunables(self) -> list[TunableParam]:
        """The EEC's (:meth:`~hil.controllers.bench.eec.EEC.tunables`)."""
        return self.eec.tunables()

    def set_tunable(self, name: str, value: Any) -> None:
        self.eec.set_tunable(name, value)

    def rebuilt(self, name: str, value: Any) -> Callable[[], None]:
        return self.eec.rebuilt(name, value)

    def decide(self, obs: BenchObservation) -> dict[str, bool]:
        # recorded at the decision instant: obs.t_s counts whole ns from the sequence origin
        t, t_ns = obs.t_s, self.origin() + round(obs.t_s * 1e9)
        estimate = obs.estimate
        self.estimate_topic.log(t_ns, {"disturbance_va": estimate.disturbance_va,
                                       "output_va": estimate.output_va,
                                       "innovation_va": estimate.innovation_va})
        decision = self.eec.step(obs)
        log = self.log
        if decision.solve is not None:
            log.solve_ms.add(decision.solve.solve_ms)
            log.solver_limits += decision.solve.status == "time_limit"
            if math.isfinite(decision.solve.gap):
                log.max_gap = max(log.max_gap, decision.solve.gap)
        for kind, message in decision.events:
            self.session.event(kind, message, level="warning", source="eec", t_s=t,
                               status=decision.solve.status if decision.solve else "")
            log.fallbacks += kind == "eec.fallback"
        plan = decision.plan
        if plan is not None:
            self.plan_topic.log(t_ns, {
                "t_s": plan.t_s, "status": plan.status, "solve_ms": plan.solve_ms,
                "gap": plan.gap, "nodes": plan.nodes, "bound": plan.bound,
                "objective": plan.objective, "peak_va": plan.peak_va,
                "energy_vas": plan.energy_vas, "rows": plan.rows,
                "u": {n: plan.u[j].tolist() for j, n in enumerate(self.problem.peripherals)},
                "q": {r.name: np.round(plan.q[j], 3).tolist()
                      for j, r in enumerate(self.problem.resources)},
                "power_va": np.round(plan.power_va, 2).tolist(),
            })
        return decision.relays


class GuardedController:
    """Any bench controller as the loop calls it: every ``decide()`` timed for the KPIs and
    held to its time budget, its answer checked (a mapping of peripheral relay names to
    booleans). An exception, a wrong answer or a late one is a
    :class:`~hil.errors.ControllerError`, recorded on ``/events``; the loop then stops
    with every relay at its safe level."""

    def __init__(self, controller: BenchController, label: str, peripherals: tuple[str, ...],
                 log: RunLog, event: EventSink, budget_s: float | None) -> None:
        self.controller, self.label, self.peripherals = controller, label, peripherals
        self.log, self.event, self.budget_s = log, event, budget_s
        self.estimator = estimator_of(controller)

    def decide(self, obs: BenchObservation) -> dict[str, bool]:
        try:
            answer, elapsed = guarded_call(self.label, "decide", self.controller.decide, obs,
                                           budget_s=self.budget_s)
            command = relay_command(answer, self.peripherals, self.label)
        except ControllerError as exc:
            self.event("controller.error", str(exc), level="error", source="controller",
                       t_s=obs.t_s)
            raise
        self.log.decide_ms.add(elapsed * 1e3)
        return command


def relay_command(answer: Any, peripherals: tuple[str, ...], label: str) -> dict[str, bool]:
    """A controller's answer as ``{relay: bool}``; anything else is a ControllerError."""
    if not isinstance(answer, Mapping):
        raise ControllerError(f"controller {label!r}: decide() must return a mapping of relay "
                              f"names to booleans, e.g. {{'P1': True}}, got "
                              f"{type(answer).__name__} {answer!r:.60}")
    command = {}
    for name, on in answer.items():
        if name not in peripherals:
            raise ControllerError(f"controller {label!r}: decide() named relay {name!r}; it may "
                                  f"switch only {', '.join(peripherals)}")
        if not isinstance(on, bool | np.bool_) and on not in (0, 1):
            raise ControllerError(f"controller {label!r}: decide() gave {name!r} the value "
                                  f"{on!r}; expected True or False")
        command[name] = bool(on)
    return command


@dataclass(frozen=True)
class BenchContext:
    """What a run gives a controller factory that takes a ``context`` argument.

    For any controller: ``problem`` (machining sequence, resources with Table I's rates and
    bounds, dwell), ``step_s`` (the decision step) and ``session``, whose
    ``topic(name, json_schema).log(t_ns, message)`` and ``event(kind, message, **data)``
    record a controller's own signals beside the run's. The rest serves the built-ins.
    """

    problem: BenchProblem
    step_s: float
    session: Session
    log: RunLog
    origin: Callable[[], int]
    eec: EecConfig               # eec.toml as the run resolved it (flags and params laid in)


class SignalLimits(Task):
    """Every sample (record phase): the per-tick limits (``--limit 'total_va<=900'``) on the meter's
    quantities and the levels. The first violation is recorded on ``/events`` and stops the
    loop; the relays then go to their safe levels."""

    def __init__(self, rig: BenchRig, watch: SignalWatch, session: Session) -> None:
        super().__init__("limits", rig.sampler.divisor)
        self.rig, self.watch, self.session = rig, watch, session

    def record(self, t_ns: int) -> None:
        sampler = self.rig.sampler
        values: dict[str, float] = {**(sampler.fresh_power or {}),
                                    **(sampler.fresh_levels or {})}
        violation = self.watch.check(values)
        if violation is not None:
            message = f"limit violated, run stopped: {violation.describe()}"
            self.session.event("limit.abort", message, level="error", source="limits",
                               limit=str(violation.limit), measured=violation.measured)
            self.session.loop.stop(f"limit {violation.limit}")
