"""The fuzz campaign's machinery: a target (a parser of hil's, its rig and its cases), the
rule every target checks, a bound that turns a hang into a failure, and the run of a target
under hypothesis, bounded for ``make test`` (deterministic, no example database) or by the
clock for ``benchmarks/fuzz.py``.

The rule: whatever the bytes, a parser gives a clear error or an exception answer (an SDO
abort, a Modbus exception, an EMCY, one line of a :class:`~hil.errors.HilError`), never
another exception, a hang or a traceback; and hil's outputs stay where the rule of each
target says (the emulated relays and drive change only as a valid request asks, the master
requests its drive's safe state).
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import seed as hypothesis_seed
from hypothesis import strategies as st

from hil.errors import HilError


class Limits:
    """How long one case may take before it counts as a hang: generous on a loaded 2-core
    machine (``make test``); the benchmark shortens it while it shrinks a finding."""

    hang_s = 10.0


LIMITS = Limits()

Check = Callable[[Any], None]


class HangError(AssertionError):
    """A case did not end within its bound."""


@dataclass(frozen=True)
class Target:
    """One parser under fuzz: ``rig()`` opens what the cases go through (a server, a port)
    and yields the check of one case; ``cases`` draws them; ``examples``: how many the bounded
    run of ``make test`` draws; ``regressions``: inputs that once broke it, always run."""

    name: str
    cases: st.SearchStrategy[Any]
    rig: Callable[[], contextlib.AbstractContextManager[Check]]
    examples: int
    regressions: tuple[Any, ...] = field(default=())


def bounded_settings(examples: int) -> settings:
    """``make test``'s settings: ``examples`` cases, the same ones on every run; a finding is
    reported as drawn, not shrunk (shrinking a hang costs its bound per try: the benchmark
    shrinks)."""
    return settings(max_examples=examples, deadline=None, derandomize=True, database=None,
                    suppress_health_check=list(HealthCheck), print_blob=False,
                    phases=(Phase.explicit, Phase.generate))


def run_target(target: Target, run_settings: settings | None = None,
               count: Callable[[], None] | None = None, seed: int | None = None) -> None:
    """Draw ``target``'s cases under ``run_settings`` (default: the bounded run) through one
    rig, from ``seed`` if given; its regressions first. The first case that breaks the rule
    raises (shrunk, where the settings shrink)."""
    with target.rig() as check:
        for case in target.regressions:
            check(case)

        def one(case: Any) -> None:
            if count is not None:
                count()
            check(case)

        run = (run_settings or bounded_settings(target.examples))(given(target.cases)(one))
        if seed is not None:
            run = hypothesis_seed(seed)(run)
        run()


@contextlib.contextmanager
def bound(what: str = "the case", seconds: float | None = None) -> Iterator[None]:
    """Raise :class:`HangError` in this (main) thread when the block runs longer than ``seconds``
    (default: the hang bound); a timer already set (pytest-timeout's) is put back with the
    time it had left."""
    seconds = LIMITS.hang_s if seconds is None else seconds
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def expired(_signum: int, _frame: Any) -> None:
        raise HangError(f"{what} did not end within {seconds:g} s")

    started = time.monotonic()
    previous_handler = signal.signal(signal.SIGALRM, expired)
    previous_left, previous_interval = signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous_handler)
        if previous_left:
            left = max(previous_left - (time.monotonic() - started), 1e-3)
            signal.setitimer(signal.ITIMER_REAL, left, previous_interval)


def clear_error(exc: BaseException, *kinds: type[BaseException]) -> None:
    """``exc`` is what the rule allows: one of ``kinds`` (default: a HilError) with a message
    of one line and no traceback in it; else it is raised again, as the finding."""
    allowed = kinds or (HilError,)
    if not isinstance(exc, allowed):
        raise exc
    text = str(exc)
    if not text.strip() or "\n" in text or "Traceback" in text:
        raise AssertionError(f"{type(exc).__name__} is not one clear line: {text!r}") from exc


class ThreadFailures:
    """Exceptions that end a thread (a server's) and records logged at ERROR or above with a
    traceback (``log.exception``), caught while installed: a server that survives a bad
    frame by logging its traceback has still crashed on it."""

    def __init__(self) -> None:
        self.items: list[str] = []
        self._hook: Any = None
        self._handler = _Collect(self.items)

    def __enter__(self) -> ThreadFailures:
        self._hook = threading.excepthook
        threading.excepthook = self._thread_died
        logging.getLogger().addHandler(self._handler)
        return self

    def __exit__(self, *_exc: object) -> None:
        threading.excepthook = self._hook
        logging.getLogger().removeHandler(self._handler)

    def _thread_died(self, args: threading.ExceptHookArgs) -> None:
        name = args.thread.name if args.thread is not None else "?"
        self.items.append(f"thread {name} died: {args.exc_type.__name__}: {args.exc_value}")

    def check(self) -> None:
        """Raise the first failure since the last check (then forget them)."""
        items, self.items[:] = list(self.items), []
        if items:
            raise AssertionError("; ".join(items))


class _Collect(logging.Handler):
    def __init__(self, items: list[str]) -> None:
        super().__init__(logging.ERROR)
        self._items = items

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info:
            kind, value, _ = record.exc_info
            self._items.append(f"{record.getMessage()}: "
                               f"{getattr(kind, '__name__', kind)}: {value}")
