"""Parameters changed while a run runs: checked, applied at a tick boundary, recorded.

Every run has one :class:`Tuner` (:func:`hil.core.run.run_experiment` makes it). The run's
application registers what may change: the controller's own parameters
(:class:`hil.controllers.base.Tunable`, as ``controller.NAME``, by :func:`add_controller`) and
its safety limits (``safety.NAME``, which may only be made stricter: :attr:`TunableSpec.stricter`).

A change is asked for with :meth:`Tuner.request` from any thread. It is checked there (a known
name, the type, the range, the safety direction, the controller's own check); a parameter that
needs a rebuild is rebuilt by the tuner's worker thread, off the loop, once the rebuilds queued
before it are in place (so it starts from the parameters in force). The change then waits in
a queue that the loop looks at once per tick, before the tick's phases
(:attr:`FixedRateLoop.at_boundary <hil.core.loop.FixedRateLoop.at_boundary>`: one look at an
empty queue when nobody tunes), and is applied at the first tick boundary (``at_tick``: not
before that tick; in lockstep at that tick, the loop waiting there for its rebuild), the
tick's number reported back. Every applied change is
an event ``param.changed`` on ``/events`` (parameter, old, new, client, tick) and a message on
``/params`` (:data:`PARAMS_SCHEMA`); a refused one an event ``param.refused`` (parameter,
value, client, reason). Both are recorded by the loop's thread.

The seam for a transport (a live view's parameters, a command-line client):
``run_experiment(experiment, tuner_started=callback)`` (and ``hil.servo.run.run_servo``,
``hil.bench.run.run_bench``, ``hil.api.run_servo|run_bench`` with ``tuner_started=``) calls
``callback(tuner)`` in the run's thread once the devices are enabled and the tasks added,
just before the loop's first tick; the transport then serves :meth:`Tuner.specs`, calls
:meth:`Tuner.request` from its own thread and follows applied changes with
:meth:`Tuner.add_listener`. After the loop ends, requests are refused ("the run has ended").
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any

from hil.controllers.base import Rebuilding, Tunable
from hil.errors import HilError

#: the topic of applied changes, and its schema: one message per change
PARAMS_TOPIC = "/params"
#: lockstep: how long the loop waits at its tick for the rebuild of a change asked for then
SCHEDULED_REBUILD_WAIT_S = 60.0
PARAMS_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.ParamChange",
    "description": "A parameter changed while the run ran, at the boundary of tick `tick`.",
    "properties": {
        "parameter": {"type": "string"},
        "old": {"type": ["number", "integer", "boolean", "string"]},
        "new": {"type": ["number", "integer", "boolean", "string"]},
        "unit": {"type": "string"},
        "client": {"type": "string", "description": "who asked for it"},
        "tick": {"type": "integer"},
    },
}

Value = float | int | bool | str


@dataclass(frozen=True)
class TunableSpec:
    """A parameter of the run that may change while it runs."""

    name: str                  # "controller.kp", "safety.following_error_deg"
    value: Value               # the value in force now
    unit: str                  # "rpm/deg", "ticks", "deg", "" ...
    minimum: float | None
    maximum: float | None
    step: float | None
    rebuild: bool              # True: rebuilt off the loop, swapped at a tick boundary
    stricter: str | None       # safety limits only: "lower" or "higher", the only way it moves
    description: str


@dataclass(frozen=True)
class TuneResult:
    """What became of one request."""

    name: str
    accepted: bool
    value: Value               # the value in force afterwards (the new one, or the one that stays)
    reason: str                # why it was refused ("" when accepted): one line
    tick: int | None           # the tick it took effect at (None when refused)


class _RefusedError(Exception):
    """A request refused, with its one-line reason."""


@dataclass
class _Entry:
    spec: TunableSpec
    apply: Callable[[Any], None]                          # at a tick boundary, loop thread
    prepare: Callable[[Any], Callable[[], None]] | None   # rebuild: off the loop -> the swap
    check: Callable[[Any], None] | None                   # raises with the reason, off the loop
    promised: Value                                       # the value once the queue is applied


class PendingChange:
    """One change asked for (:meth:`Tuner.submit`): queued, or a refusal waiting to be
    recorded; :meth:`Tuner.wait` gives its answer."""

    def __init__(self, entry: _Entry | None, name: str, value: Any, client: str,
                 at_tick: int | None, swap: Callable[[], None] | None,
                 refused: TuneResult | None = None) -> None:
        self.entry, self.name, self.value, self.client = entry, name, value, client
        self.at_tick, self.swap = at_tick, swap
        self.asked_at = -1                # the last tick boundary before it was asked for
        self.refused = refused           # a refusal, queued only to be recorded
        self.cancelled = False
        self.result: TuneResult | None = refused
        self.done = threading.Event()
        self.prepared = threading.Event()  # rebuilt (or refused): nothing left off the loop


class Tuner:
    """The run's tunable parameters and the queue of changes to them (thread-safe)."""

    def __init__(self, *, event: Callable[..., None] | None = None,
                 topic: Callable[[str, dict[str, Any]], Any] | None = None,
                 time_ns: Callable[[], int] | None = None, lockstep: bool = False) -> None:
        self._entries: dict[str, _Entry] = {}
        # lockstep: a change asked for at a tick is applied at that tick, its rebuild waited
        # for there (the session the same however long the rebuild takes on the wall clock)
        self._lockstep = lockstep
        self._scheduled: list[PendingChange] = []  # rebuilds asked for at a tick, not prepared
        self._queue: deque[PendingChange] = deque()
        self._lock = threading.Lock()            # the entries and the queue
        self._requests = threading.Lock()        # one request checked at a time
        self._listeners: list[Callable[[TuneResult], None]] = []
        self._event, self._topic, self._time_ns = event, topic, time_ns
        self._params: Any = None                 # the /params topic, made at the first change
        self.now = -1                            # the last tick boundary the loop reached
        self._ended = False
        self._rebuilds: deque[PendingChange] = deque()   # waiting for the worker
        self._work = threading.Condition(self._lock)
        self._worker: threading.Thread | None = None
        self.applied = 0                         # changes applied so far

    # -- what may change -------------------------------------------------------------------
    def add(self, spec: TunableSpec, apply: Callable[[Any], None], *,
            prepare: Callable[[Any], Callable[[], None]] | None = None,
            check: Callable[[Any], None] | None = None) -> None:
        """Register a parameter: ``apply(value)`` at a tick boundary, or, for a ``rebuild``
        one, ``prepare(value)`` off the loop, returning the swap run at the boundary.
        ``check(value)`` (optional) raises with a one-line reason to refuse a value."""
        if spec.rebuild and prepare is None:
            raise ValueError(f"tunable {spec.name}: a rebuild parameter needs prepare")
        with self._lock:
            if spec.name in self._entries:
                raise ValueError(f"duplicate tunable {spec.name!r}")
            self._entries[spec.name] = _Entry(spec, apply, prepare, check, spec.value)

    def specs(self) -> list[TunableSpec]:
        """Every parameter, with the value in force now, in the order they were added."""
        with self._lock:
            return [entry.spec for entry in self._entries.values()]

    def add_listener(self, callback: Callable[[TuneResult], None]) -> None:
        """``callback(result)`` for every applied change, from the loop's thread: keep it
        cheap (hand the result to your own thread)."""
        with self._lock:
            self._listeners.append(callback)

    # -- asking ----------------------------------------------------------------------------
    def request(self, name: str, value: object, client: str, timeout_s: float = 5.0, *,
                at_tick: int | None = None) -> TuneResult:
        """Check ``value`` for ``name``, queue it, and wait until the loop applied it at a
        tick boundary (or after its rebuild) or it was refused; ``at_tick``: not before that
        tick. Not applied within ``timeout_s``: refused, and withdrawn."""
        pending = self.submit(name, value, client, at_tick=at_tick)
        return self.wait(pending, timeout_s)

    def submit(self, name: str, value: object, client: str, *,
               at_tick: int | None = None) -> PendingChange:
        """:meth:`request` without the wait: the change checked and queued (its rebuild
        done); :meth:`wait` gives its result."""
        asked_at = self.now
        with self._requests:
            with self._lock:
                entry = self._entries.get(name)
                ended = self._ended
            try:
                if ended:
                    raise _RefusedError("the run has ended")
                if entry is None:
                    known = ", ".join(self._entries) or "none"
                    raise _RefusedError(f"no tunable parameter {name!r} (known: {known})")
                checked = _coerce(entry.spec, value)
                _check_direction(entry.spec, entry.promised, checked)
                _check_range(entry.spec, checked)
                if entry.check is not None:
                    entry.check(checked)
            except (_RefusedError, HilError, ValueError) as exc:
                return self._refuse(entry, name, value, client, str(exc))
            pending = PendingChange(entry, name, checked, client, at_tick, None)
            pending.asked_at = asked_at
            with self._lock:
                ended = self._ended
                if not ended:
                    entry.promised = checked
                    if entry.prepare is None:
                        self._queue.append(pending)
                    else:  # rebuilt by the worker, then queued
                        self._rebuilds.append(pending)
                        if self._lockstep and at_tick is not None:
                            self._scheduled.append(pending)
                        self._start_worker()
                        self._work.notify()
            if ended:
                return self._refuse(entry, name, value, client, "the run has ended")
            return pending

    def _start_worker(self) -> None:
        if self._worker is None:
            self._worker = threading.Thread(target=self._rebuild_all, name="hil-tuner-rebuild",
                                            daemon=True)
            self._worker.start()

    def _rebuild_all(self) -> None:
        """The worker: each rebuild in turn, once the swaps queued before it are in place
        (so it starts from the parameters in force), then queued for the loop."""
        while True:
            with self._work:
                while not self._rebuilds and not self._ended:
                    self._work.wait()
                if self._ended:
                    return
                pending = self._rebuilds.popleft()
                before = [p for p in self._queue if p.swap is not None]
            for queued in before:
                queued.done.wait()
            if pending.cancelled:
                continue
            entry = pending.entry
            assert entry is not None and entry.prepare is not None
            try:
                swap = entry.prepare(pending.value)
            except (HilError, ValueError) as exc:
                with self._lock:
                    if pending.result is None:
                        entry.promised = entry.spec.value
                        pending.result = pending.refused = TuneResult(
                            pending.name, False, entry.spec.value, str(exc), None)
                        if not self._ended:
                            self._queue.append(pending)  # recorded by the loop's thread
                pending.prepared.set()
                pending.done.set()
                continue
            with self._lock:
                if not pending.cancelled and not self._ended:
                    pending.swap = swap
                    self._queue.append(pending)
                    pending.prepared.set()
                    continue
                if pending.result is None:  # the run ended while it was rebuilt
                    pending.result = TuneResult(pending.name, False, entry.spec.value,
                                                "the run ended before it was applied", None)
            pending.prepared.set()
            pending.done.set()

    def wait(self, pending: PendingChange, timeout_s: float) -> TuneResult:
        """The result of a submitted change; withdrawn (refused) if not applied in time."""
        if not pending.done.wait(timeout_s):
            with self._lock:
                if pending.result is None:
                    pending.cancelled = True
                    entry = pending.entry
                    assert entry is not None
                    entry.promised = entry.spec.value
                    pending.result = TuneResult(
                        pending.name, False, entry.spec.value,
                        f"not applied within {timeout_s:g} s: the loop reached no tick "
                        "boundary", None)
                    pending.prepared.set()
                    pending.done.set()
        assert pending.result is not None
        return pending.result

    def _refuse(self, entry: _Entry | None, name: str, value: object, client: str,
                reason: str) -> PendingChange:
        stays = entry.spec.value if entry is not None else ""
        result = TuneResult(name, False, stays, reason, None)
        pending = PendingChange(entry, name, value, client, None, None, refused=result)
        pending.done.set()
        with self._lock:
            if not self._ended:
                self._queue.append(pending)  # recorded by the loop's thread
        return pending

    # -- the loop's side -------------------------------------------------------------------
    def _await_scheduled(self, n: int) -> None:
        """Lockstep: the rebuilds asked for at tick ``n`` or before, waited for here in turn
        (for up to :data:`SCHEDULED_REBUILD_WAIT_S` each: one that takes longer is applied when
        done). What is ready is applied before each wait: the next rebuild starts from it."""
        with self._lock:
            due = [p for p in self._scheduled if p.at_tick is not None and p.at_tick <= n]
            self._scheduled = [p for p in self._scheduled if p not in due]
        for pending in due:
            self._apply_due(n)
            pending.prepared.wait(SCHEDULED_REBUILD_WAIT_S)

    def tick(self, n: int) -> None:
        """At the boundary of tick ``n`` (the loop's thread): apply what is due."""
        self.now = n
        if self._scheduled:
            self._await_scheduled(n)
        if self._queue:
            self._apply_due(n)

    def _apply_due(self, n: int) -> None:
        """Apply (or record the refusal of) every queued change due at tick ``n``."""
        with self._lock:
            due = [p for p in self._queue if p.at_tick is None or p.at_tick <= n]
            for pending in due:
                self._queue.remove(pending)
            listeners = list(self._listeners)
            for pending in due:
                if pending.refused is not None:
                    self._record_refused(pending)
                    pending.result = pending.refused
                elif not pending.cancelled:
                    self._apply(pending, n)
        for pending in due:
            result = pending.result
            if result is not None and result.accepted and result.tick == n:
                for listener in listeners:
                    listener(result)
            pending.done.set()

    def _apply(self, pending: PendingChange, n: int) -> None:
        entry = pending.entry
        assert entry is not None
        old = entry.spec.value
        try:
            if pending.swap is not None:
                pending.swap()
            else:
                entry.apply(pending.value)
        except (HilError, ValueError) as exc:
            entry.promised = old
            pending.result = TuneResult(pending.name, False, old, str(exc), None)
            self._record(pending, "param.refused", f"{pending.name} = {pending.value!r} "
                         f"refused: {exc}", level="warning", value=pending.value,
                         reason=str(exc))
            return
        entry.spec = replace(entry.spec, value=pending.value)
        self.applied += 1
        pending.result = TuneResult(pending.name, True, pending.value, "", n)
        unit = entry.spec.unit
        self._record(pending, "param.changed", f"{pending.name}: {old!r} -> "
                     f"{pending.value!r}{' ' + unit if unit else ''} at tick {n}",
                     old=old, new=pending.value, tick=n, asked_at_tick=pending.asked_at)
        if self._topic is not None and self._time_ns is not None:
            if self._params is None:
                self._params = self._topic(PARAMS_TOPIC, PARAMS_SCHEMA)
            self._params.log(self._time_ns(), {
                "parameter": pending.name, "old": old, "new": pending.value, "unit": unit,
                "client": pending.client, "tick": n})

    def _record_refused(self, pending: PendingChange) -> None:
        result = pending.refused
        assert result is not None
        value = pending.value if isinstance(pending.value, (bool, int, float, str)) \
            else repr(pending.value)
        self._record(pending, "param.refused", f"{pending.name} = {value!r} refused: "
                     f"{result.reason}", level="warning", value=value, reason=result.reason)

    def _record(self, pending: PendingChange, kind: str, message: str, level: str = "info",
                **data: Any) -> None:
        if self._event is not None:
            self._event(kind, message, level=level, source="tuner", parameter=pending.name,
                        client=pending.client, **data)

    def close(self) -> None:
        """The run has ended: what is still queued is refused (refusals still recorded
        by :meth:`tick` are dropped), and so is every later request."""
        with self._lock:
            self._ended = True
            self._work.notify_all()
            left = list(self._queue) + list(self._rebuilds)
            self._queue.clear()
            self._rebuilds.clear()
            self._scheduled.clear()
            for pending in left:
                if pending.result is None:
                    entry = pending.entry
                    assert entry is not None
                    pending.result = TuneResult(pending.name, False, entry.spec.value,
                                                "the run ended before it was applied", None)
        for pending in left:
            pending.prepared.set()
            pending.done.set()


def _coerce(spec: TunableSpec, value: object) -> Value:
    """``value`` as the type of ``spec``'s (a number from text too); else refused."""
    kind = type(spec.value)
    unit = f" [{spec.unit}]" if spec.unit else ""
    if kind is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false"):
            return value.lower() == "true"
        raise _RefusedError(f"{spec.name} takes true or false, got {value!r}")
    if kind is str:
        if isinstance(value, str):
            return value
        raise _RefusedError(f"{spec.name} takes text, got {value!r}")
    number: float
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise _RefusedError(f"{spec.name} takes a number{unit}, got {value!r}")
    try:
        number = float(value)
    except ValueError:
        raise _RefusedError(f"{spec.name} takes a number{unit}, got {value!r}") from None
    if not math.isfinite(number):
        raise _RefusedError(f"{spec.name} takes a finite number{unit}, got {value!r}")
    if kind is int:
        if number != int(number):
            raise _RefusedError(f"{spec.name} takes a whole number{unit}, got {value!r}")
        return int(number)
    return number


def _check_range(spec: TunableSpec, value: Value) -> None:
    if isinstance(value, (bool, str)):
        return
    unit = f" {spec.unit}" if spec.unit else ""
    low = -math.inf if spec.minimum is None else spec.minimum
    high = math.inf if spec.maximum is None else spec.maximum
    if not low <= value <= high:
        raise _RefusedError(f"{spec.name} = {value:g}{unit} is outside its range "
                       f"[{low:g}, {high:g}]{unit}")


def _check_direction(spec: TunableSpec, now: Value, value: Value) -> None:
    """A safety limit moves only the stricter way while running."""
    if spec.stricter is None or isinstance(value, (bool, str)) or isinstance(now, (bool, str)):
        return
    unit = f" {spec.unit}" if spec.unit else ""
    if (spec.stricter == "lower" and value > now) or (spec.stricter == "higher" and value < now):
        way = "lowered" if spec.stricter == "lower" else "raised"
        raise _RefusedError(f"{spec.name} is a safety limit: while running it may only be {way} "
                       f"(stricter), now {now:g}{unit}, asked {value:g}{unit}")


def add_controller(tuner: Tuner, controller: object, prefix: str = "controller") -> int:
    """Register a :class:`~hil.controllers.base.Tunable` controller's parameters as
    ``PREFIX.NAME``; how many (0 for a controller without the capability)."""
    if not isinstance(controller, Tunable):
        return 0
    params = list(controller.tunables())
    for param in params:
        name = param.name

        def apply(value: Any, name: str = name) -> None:
            controller.set_tunable(name, value)

        prepare = None
        if param.rebuild:
            if not isinstance(controller, Rebuilding):
                raise ValueError(f"tunable {prefix}.{name}: a rebuild parameter needs the "
                                 "controller's rebuilt(name, value)")

            def prepare(value: Any, name: str = name) -> Callable[[], None]:
                return controller.rebuilt(name, value)

        own_check = getattr(controller, "check_tunable", None)
        check = None
        if callable(own_check):
            def check(value: Any, name: str = name, own: Callable[..., Any] = own_check
                      ) -> None:
                own(name, value)

        tuner.add(TunableSpec(f"{prefix}.{name}", param.value, param.unit, param.minimum,
                              param.maximum, param.step, param.rebuild, None,
                              param.description), apply, prepare=prepare, check=check)
    return len(params)


def add_safety_limits(tuner: Tuner, limits: object,
                      stricter: Mapping[str, tuple[str, str, str]],
                      tighten: Callable[[str, float], None], signed: str) -> None:
    """Register each limit of ``stricter`` (``{NAME: (unit, "lower"|"higher", description)}``)
    that ``limits`` holds as ``safety.NAME``: movable only towards its stricter side, from the
    value in force, and applied by ``tighten(NAME, value)``. Limits named ``signed...`` may be
    of either sign (a position, a level); the others are at least 0."""
    for name, (unit, direction, description) in stricter.items():
        now = float(getattr(limits, name))
        low = None if direction == "higher" or name.startswith(signed) else 0.0
        high = None if direction == "higher" else now

        def apply(value: Any, name: str = name) -> None:
            tighten(name, float(value))

        tuner.add(TunableSpec(f"safety.{name}", now, unit, low, high, None, False, direction,
                              description), apply)

