"""The controller contracts: one per application. Every built-in controller implements its
application's protocol, the runs are typed against it, and a user's controller needs nothing
more (no base class to inherit: any class with these methods will do).

Relay bench (energy paper), decided once per decision step (1 s by default)::

    class MyBenchController:
        def decide(self, obs: BenchObservation) -> Mapping[str, bool]: ...

Servo drive (servo paper), stepped every tick (500 us, or the cycle period it says)::

    class MyServoController:
        position_input = "wrapped"                                      # optional, see below
        output = "current"                                              # optional, see below
        cycle_periods_us = (500, 1000)                                  # optional, see below
        def step(self, position_deg: float, t_s: float) -> float: ...   # current [mA]
        def reset(self) -> None: ...                                    # optional

``position_deg`` is what the controller's :class:`PositionInput` says: the spindle's angle in
[0, 360) by default, or the multi-turn position. What ``step`` returns is what its
:class:`Output` says: a current [mA] by default (the drive in CST), or a position [deg] or a
velocity [deg/s] for a drive that closes its own loop (CSP, CSV).

Controllers compute; they never touch I/O or a clock. What they ask for goes through the
drivers' safety layers (relay dwell and safe levels, the drive's current clamp), which no
controller can bypass.

Everything else a run reads from a controller is an optional capability declared here, checked
with ``isinstance`` (the built-ins have them; a user's controller may):

* bench: :class:`Estimating` (an estimator fed every sample);
* servo: :class:`CyclePeriods` (the cycle periods it runs at, declared by its factory),
  :class:`PositionInput` (wrapped or multi-turn positions), :class:`Output` (what ``step``
  returns: a current, a position or a velocity), :class:`Predicting`
  (recorded to ``/mpc/prediction``), a ``solver`` with a
  :class:`SolverReport` (the path of each step, counted), :class:`ReportsEvents` (events the
  controller raised, recorded to ``/events``), :class:`CountsFallbacks`, and a ``config``
  with :class:`MpcHorizons` (recorded with the KPIs);
* both: :class:`Resettable`, :class:`Tunable` (parameters that may change while it runs,
  each a :class:`TunableParam`; those that need a rebuild through :class:`Rebuilding`).
"""

from __future__ import annotations

from collections.abc import Callable, Container, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar, runtime_checkable

from hil.controllers.errors import ControllerSetupError


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


#: the cycle period of a servo controller that does not say it runs at others [us]
DEFAULT_PERIOD_US = 500


@runtime_checkable
class CyclePeriods(Protocol):
    """A servo controller's factory - its class, or a factory function marked with
    :func:`runs_at` - that says the cycle periods (``master.cycle_period_us``) it runs at, as
    ``cycle_periods_us``: any container of whole microseconds, e.g. ``(500, 1000)`` or
    ``range(500, 10_001, 500)`` (the multiples of 500 us up to 10 ms). Without it a controller
    runs at :data:`DEFAULT_PERIOD_US` only (whatever its design period, hil cannot know it).
    A factory that takes a ``context`` argument is told the run's period as
    ``context.period_s``; ``step``'s ``t_s`` advances by it too."""

    cycle_periods_us: Container[int]


Factory = TypeVar("Factory", bound=Callable[..., Any])


def runs_at(periods_us: Container[int]) -> Callable[[Factory], Factory]:
    """Mark a factory function with the cycle periods its controllers run at
    (:class:`CyclePeriods`; a class says it with a class attribute)."""
    def mark(factory: Factory) -> Factory:
        factory.cycle_periods_us = periods_us  # type: ignore[attr-defined]
        return factory
    return mark


def cycle_periods_of(factory: object) -> Container[int]:
    """The periods ``factory``'s controllers run at [us]: its ``cycle_periods_us``, else
    :data:`DEFAULT_PERIOD_US` only."""
    return factory.cycle_periods_us if isinstance(factory, CyclePeriods) \
        else (DEFAULT_PERIOD_US,)


def check_cycle_period(factory: object, label: str, period_us: int) -> None:
    """A ControllerSetupError naming the controller when it does not run at ``period_us``."""
    periods = cycle_periods_of(factory)
    if period_us in periods:
        return
    if not isinstance(factory, CyclePeriods):
        raise ControllerSetupError(
            f"controller {label!r} does not say it runs at a cycle period of "
   f"{period_us} us (master.cycle_period_us): a controller without "
   f"cycle_periods_us runs at {DEFAULT_PERIOD_US} us only")
    raise ControllerSetupError(
        f"controller {label!r} does not run at a cycle period of {period_us} us "
f"(master.cycle_period_us): it runs at {describe_periods(periods)}")


def describe_periods(periods: Container[int]) -> str:
    """``(500,)`` -> ``500 us``; ``range(500, 10001, 500)`` -> ``multiples of 500 us up to
    10000 us``."""
    if isinstance(periods, range) and len(periods) > 1:
        start, step, last = periods.start, periods.step, periods[-1]
        if start == step:
            return f"multiples of {step} us up to {last} us"
        return f"{start} to {last} us in steps of {step} us"
    if isinstance(periods, (tuple, list, set, frozenset, range)):
        return ", ".join(f"{p} us" for p in sorted(periods)) or "no period"
    return f"the periods of its cycle_periods_us ({periods!r})"


#: the positions a servo controller may ask for (:class:`PositionInput`)
WRAPPED, UNWRAPPED = "wrapped", "unwrapped"


@runtime_checkable
class PositionInput(Protocol):
    """A servo controller that says which position its ``step`` is given, as its
    ``position_input`` (a class attribute will do):

    * ``"wrapped"`` (also the default, without the attribute): the spindle's angle,
      ``position % 360`` in [0, 360), as the papers' controllers take it (they unwrap it
      themselves and follow the reference's nearest turn);
    * ``"unwrapped"``: the multi-turn position the master counts (turns included, in the frame
      of the run's reference: the same numbers as ``/drive/feedback``'s ``position_deg``).

    A multi-axis controller (``multi_axis = True``) says it for every axis' position."""

    position_input: str


def position_input_of(controller: object, label: str = "") -> str:
    """:data:`WRAPPED` or :data:`UNWRAPPED`: the controller's ``position_input``, wrapped
    when it has none; any other value is a ControllerSetupError naming the two (and ``label``)."""
    value = controller.position_input if isinstance(controller, PositionInput) else WRAPPED
    if value not in (WRAPPED, UNWRAPPED):
        named = f"controller {label!r}: " if label else ""
        raise ControllerSetupError(f"{named}position_input = {value!r}: a servo controller takes "
                          f"{WRAPPED!r} (position % 360, the default) or {UNWRAPPED!r} "
                          "(multi-turn) positions")
    return str(value)


#: what a servo controller's ``step`` may return (:class:`Output`), and its unit
CURRENT, POSITION, VELOCITY = "current", "position", "velocity"
OUTPUT_UNITS = {CURRENT: "mA", POSITION: "deg", VELOCITY: "deg/s"}


@runtime_checkable
class Output(Protocol):
    """A servo controller that says what its ``step`` returns, as its ``output`` (a class
    attribute will do):

    * ``"current"`` (also the default, without the attribute): the motor current [mA], which
      the drive applies (CST);
    * ``"position"``: where the axis is to be [deg], multi-turn, in the frame of the position
      the controller is given (``position_input = "unwrapped"``'s); the drive closes its own
      loop (CSP);
    * ``"velocity"``: how fast it is to turn [deg/s] (CSV, PV).

    A run refuses a controller whose output is not what the drive's mode takes, before it
    opens anything: a factory says what its controllers return as ``outputs`` (a class's
    ``output`` says it for the class; :func:`returns` marks a factory function); one that
    can return several is told the run's as ``context.output``."""

    output: str


def returns(*outputs: str) -> Callable[[Factory], Factory]:
    """Mark a factory function with what its controllers' ``step`` may return
    (:class:`Output`)."""
    def mark(factory: Factory) -> Factory:
        factory.outputs = outputs  # type: ignore[attr-defined]
        return factory
    return mark


def outputs_of(factory: object) -> tuple[str, ...]:
    """What ``factory``'s controllers may return: its ``outputs``, a class's ``output``, else
    a current."""
    outputs = getattr(factory, "outputs", None)
    if outputs is None:
        outputs = (factory.output,) if isinstance(factory, Output) else (CURRENT,)
    return tuple(outputs)


def output_of(controller: object, label: str = "") -> str:
    """:data:`CURRENT`, :data:`POSITION` or :data:`VELOCITY`: the controller's ``output``, a
    current when it has none; any other value is a ControllerSetupError naming the three (and
    ``label``)."""
    value = controller.output if isinstance(controller, Output) else CURRENT
    if value not in OUTPUT_UNITS:
        named = f"controller {label!r}: " if label else ""
        raise ControllerSetupError(f"{named}output = {value!r}: a servo controller returns a "
                                   f"{CURRENT!r} [mA] (the default), a {POSITION!r} [deg] or a "
                                   f"{VELOCITY!r} [deg/s]")
    return str(value)


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


@dataclass(frozen=True)
class TunableParam:
    """A parameter a controller lets change while it runs (:class:`Tunable`): its ``name``
    (as ``controller.NAME`` names it), the ``value`` in force, its ``unit``, the range
    ``[minimum, maximum]`` and ``step`` (None: unbounded, any), and whether a change needs a
    ``rebuild`` (built off the loop by :meth:`Rebuilding.rebuilt`, swapped in at a tick
    boundary) or applies at once (:meth:`Tunable.set_tunable`, at a tick boundary)."""

    name: str
    value: float | int | bool | str
    unit: str = ""
    minimum: float | None = None
    maximum: float | None = None
    step: float | None = None
    rebuild: bool = False
    description: str = ""


@runtime_checkable
class Tunable(Protocol):
    """A controller with parameters that may change while it runs: ``tunables()`` lists them
    with the values in force; ``set_tunable(name, value)`` applies one that needs no rebuild
    (called in the loop thread, between two steps: it must be cheap). A value it cannot take
    raises a ControllerSetupError naming the problem; the run's tuner refuses the change with
    that line. ``check_tunable(name, value)``, if the controller has it, is asked first, off
    the loop (e.g. whether the loop stays stable)."""

    def tunables(self) -> Sequence[TunableParam]: ...

    def set_tunable(self, name: str, value: Any) -> None: ...


@runtime_checkable
class Rebuilding(Protocol):
    """A :class:`Tunable` controller with parameters that need a rebuild (an MPC's horizons
    change its QP's size): ``rebuilt(name, value)`` builds the new parts off the loop thread
    and returns the swap, a cheap callable the loop runs at a tick boundary to put them in
    place (keeping the controller's state: its estimate, its last command)."""

    def rebuilt(self, name: str, value: Any) -> Callable[[], None]: ...
