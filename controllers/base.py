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
"""

from __future__ import annotations

from collections.abc import Mapping
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
