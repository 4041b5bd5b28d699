"""The controller contracts: one per application. Every built-in controller implements its
application's protocol, the runs are typed against it, and a user's controller needs nothing
more (no base class to inherit: any class with these methods will do).

Relay bench (energy paper), decided once per decision step (1 s by default)::

    class MyBenchController:
        def decide(self, obs: BenchObservation) -> Mapping[str, bool]: ...

Servo drive (servo paper), stepped every tick (500 us)::

    class MyServoController:
        def step(self, position_deg: float, t_s: float) -> float: ...   # current [mA]
        def reset(self) -> None: ...                                    # optional

Controllers compute; they never touch I/O or a clock. What they ask for goes through the
drivers' safety layers (relay dwell and safe levels, the drive's current clamp), which no
controller can bypass.

Everything else a run reads from a controller is an optional capability declared here, checked
with ``isinstance`` (the built-ins have them; a user's controller may):

* bench: :class:`Estimating` (an estimator fed every sample);
* servo: :class:`Predicting` (recorded to ``/mpc/prediction``), a ``solver`` with a
  :class:`SolverReport` (the path of each step, counted), :class:`ReportsEvents` (events the
  controller raised, recorded to ``/events``), :class:`CountsFallbacks`, and a ``config``
  with :class:`MpcHorizons` (recorded with the KPIs);
* both: :class:`Resettable`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable


@dataclass(frozen=True)
class BenchObservation:
    """What a bench controller is told at a decision instant."""

    t_s: float                     # time since the machining sequence started [s]
    levels: Mapping[str, float]    # resource levels q_j by name ("q1", "q2")
    relays: Mapping[str, bool]     # actual states of the peripheral relays ("P1", "P2")
    power_va: float                # latest total apparent power of the meter [VA]
    estimate: Any = None           # the controller's own estimator's output (see BenchEstimator)


@dataclass(frozen=True)
class BenchSample:
    """One meter sample (every sampling period, 10 ms by default), for an estimator."""

    t_s: float                     # time since the machining sequence started [s]
    power_va: float | None         # total apparent power [VA]; None: this poll failed
    relays: Mapping[str, bool]     # actual states of every relay (machining and peripheral)


@runtime_checkable
class BenchEstimator(Protocol):
    """A state estimator that runs at the sampling rate, in the loop thread, for a bench
    controller that provides one as its ``estimator`` attribute (the EEC's Kalman filter).
    Its ``estimate()`` at the decision instant becomes ``BenchObservation.estimate``."""

    def update(self, sample: BenchSample) -> None: ...

    def estimate(self) -> Any: ...


@runtime_checkable
class Estimating(Protocol):
    """A bench controller with an ``estimator`` (a :class:`BenchEstimator`) that the run feeds
    every sample."""

    estimator: Any


def estimator_of(controller: object) -> BenchEstimator | None:
    """The controller's estimator, if it has one that is a :class:`BenchEstimator`."""
    estimator = controller.estimator if isinstance(controller, Estimating) else None
    return estimator if isinstance(estimator, BenchEstimator) else None


@runtime_checkable
class BenchController(Protocol):
    """Decides the peripheral relays from an observation: ``{"P1": True, ...}``. Relays it
    leaves out keep their state."""

    def decide(self, obs: BenchObservation) -> Mapping[str, bool]: ...


@runtime_checkable
class ServoController(Protocol):
    """Called once per tick with the measured position; returns the current command [mA]."""

    def step(self, position_deg: float, t_s: float) -> float: ...


@runtime_checkable
class Resettable(Protocol):
    """A controller with state to clear before a run (optional part of the contracts)."""

    def reset(self) -> None: ...


@runtime_checkable
class Predicting(Protocol):
    """A servo controller that tells its predicted inputs u(k+i|k) [mA] and outputs
    y(k+i|k) [deg] after each step (the MPCs): recorded to ``/mpc/prediction``."""

    def prediction(self) -> tuple[Any, Any]: ...


@runtime_checkable
class SolverReport(Protocol):
    """A controller's ``solver``: the path of the last step (``unconstrained``, ``qp``,
    ``explicit``, ``fallback``...) and how often each path was taken."""

    last_path: str
    counts: Mapping[str, int]


def solver_of(controller: object) -> SolverReport | None:
    """The controller's ``solver`` report, if it has one."""
    solver = getattr(controller, "solver", None)
    return solver if isinstance(solver, SolverReport) else None


@runtime_checkable
class ReportsEvents(Protocol):
    """A controller that raises events (the explicit MPC's fallbacks): each a mapping with
    ``kind``, ``message``, optionally ``level`` and data, taken once."""

    def pop_events(self) -> Sequence[Mapping[str, Any]]: ...


@runtime_checkable
class CountsFallbacks(Protocol):
    """A controller that counts the steps it fell back to a slower or safer path."""

    fallbacks: int


@runtime_checkable
class MpcHorizons(Protocol):
    """The horizons of a model-predictive controller, as its ``config`` holds them: extended
    reference (``foh`` | ``zoh``), trajectory, control and prediction horizons."""

    ert: str
    ht: int
    hu: int
    hp: int


def horizons_of(controller: object) -> MpcHorizons | None:
    """The controller's MPC horizons (its ``config``), if it has them."""
    config = getattr(controller, "config", None)
    return config if isinstance(config, MpcHorizons) else None
