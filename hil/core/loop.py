"""FixedRateLoop: one base period, tasks running every ``divisor`` ticks, read -> compute -> write.

Overrun policy: when the loop wakes up one or more whole base periods after a tick's deadline,
the ticks whose slots have passed are skipped and counted (per task, as ``missed``); the
schedule stays on its absolute grid, so the loop never drifts. In real time, a task whose step
takes longer than its own period is counted in ``overruns`` (in lockstep, compute time is
reported but costs no virtual time). SIGINT/SIGTERM stop the loop at the next tick boundary;
every component's ``safe_state()`` runs before :meth:`FixedRateLoop.run` returns, also on errors.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

from hil.core.clock import Clock
from hil.core.stats import TimingHistogram

# While a real-time loop runs, another thread holding the GIL is forced to hand it over after
# this long (CPython's default is 5 ms: ten 2 kHz ticks lost behind the recorder's writer).
REALTIME_SWITCH_INTERVAL_S = 1e-4


class SafeStateful(Protocol):
    def safe_state(self) -> None: ...


class Task:
    """One job of the loop. Subclass and override the three phases (all optional).

    ``read`` returns a measurement, ``compute`` turns it into a command, ``write`` applies it.
    ``safe_state`` puts whatever this task drives into its safe state; it must be idempotent.
    """

    def __init__(self, name: str, divisor: int = 1) -> None:
        if not name or "/" in name:
            raise ValueError(f"task name must be non-empty without '/': {name!r}")
        if int(divisor) != divisor or divisor < 1:
            raise ValueError(f"task {name!r}: divisor must be a positive integer, got {divisor!r}")
        self.name = name
        self.divisor = int(divisor)

    def read(self, t_ns: int) -> Any:
        return None

    def compute(self, measurement: Any, t_ns: int) -> Any:
        return None

    def write(self, command: Any, t_ns: int) -> None:
        return None

    def safe_state(self) -> None:
        return None


class FunctionTask(Task):
    """A task made of plain callables, for small jobs and tests."""

    def __init__(
        self,
        name: str,
        divisor: int = 1,
        read: Callable[[int], Any] | None = None,
        compute: Callable[[Any, int], Any] | None = None,
        write: Callable[[Any, int], None] | None = None,
        safe_state: Callable[[], None] | None = None,
    ) -> None:
        super().__init__(name, divisor)
        self._read, self._compute, self._write, self._safe = read, compute, write, safe_state

    def read(self, t_ns: int) -> Any:
        return self._read(t_ns) if self._read else None

    def compute(self, measurement: Any, t_ns: int) -> Any:
        return self._compute(measurement, t_ns) if self._compute else measurement

    def write(self, command: Any, t_ns: int) -> None:
        if self._write:
            self._write(command, t_ns)

    def safe_state(self) -> None:
        if self._safe:
            self._safe()


@dataclass
class TaskStats:
    """Timing of one task over a whole run (lateness and compute in us)."""

    name: str
    period_s: float
    runs: int = 0
    missed: int = 0
    overruns: int = 0
    lateness: TimingHistogram = field(default_factory=TimingHistogram)
    compute: TimingHistogram = field(default_factory=TimingHistogram)
    first_start_ns: int | None = None
    last_start_ns: int | None = None

    def measured_period_s(self) -> float:
        if self.runs < 2 or self.first_start_ns is None or self.last_start_ns is None:
            return 0.0
        return (self.last_start_ns - self.first_start_ns) / (self.runs - 1) / 1e9

    def summary(self) -> dict[str, Any]:
        return {
            "period_s": self.period_s,
            "measured_period_s": round(self.measured_period_s(), 9),
            "runs": self.runs,
            "missed": self.missed,
            "overruns": self.overruns,
            "lateness_us": self.lateness.summary(),
            "compute_us": self.compute.summary(),
        }


class _Window:
    """Samples of one task since the last timing record (handed to the recorder as-is)."""

    __slots__ = ("compute_us", "lateness_us", "missed", "overruns")

    def __init__(self) -> None:
        self.lateness_us: list[float] = []
        self.compute_us: list[float] = []
        self.missed = 0
        self.overruns = 0


TIMING_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.LoopTiming",
    "description": "Per-task timing of the fixed-rate loop over one window (about 1 s).",
    "properties": {
        "task": {"type": "string"},
        "period_s": {"type": "number"},
        "runs": {"type": "integer"},
        "missed": {"type": "integer", "description": "scheduled runs skipped in this window"},
        "overruns": {"type": "integer", "description": "steps longer than the task period"},
        "lateness_us": {"type": "array", "items": {"type": "number", "x-cdr": "float32"}},
        "compute_us": {"type": "array", "items": {"type": "number", "x-cdr": "float32"}},
    },
}


class FixedRateLoop:
    """Runs tasks on an absolute time grid given by a :class:`~hil.core.clock.Clock`.

    ``recorder`` (optional) receives one ``/loop/<task>/timing`` message per task and window.
    ``on_event`` (optional) is told about stops and skipped ticks: ``on_event(kind, msg, data)``.
    """

    def __init__(
        self,
        clock: Clock,
        base_period_s: float,
        tasks: Iterable[Task] = (),
        *,
        recorder: Any = None,
        on_event: Callable[[str, str, dict[str, Any]], None] | None = None,
        stats_window_s: float = 1.0,
        handle_signals: bool = True,
    ) -> None:
        if not base_period_s > 0:
            raise ValueError(f"base period must be > 0 s, got {base_period_s!r}")
        self.clock = clock
        self.base_period_ns = round(base_period_s * 1e9)
        self.tasks: list[Task] = []
        self.components: list[SafeStateful] = []
        self.stats: dict[str, TaskStats] = {}
        self._recorder = recorder
        self._timing_topics: dict[str, Any] = {}
        self._on_event = on_event
        self._window_ticks = max(1, round(stats_window_s * 1e9 / self.base_period_ns))
        self._handle_signals = handle_signals
        self._stop = threading.Event()
        self.stop_reason: str | None = None
        self.ticks = 0
        self.skipped_ticks = 0
        self.start_ns = 0  # clock time of tick 0's deadline: the origin of the schedule grid
        for task in tasks:
            self.add_task(task)

    # -- configuration -------------------------------------------------------------------
    def add_task(self, task: Task) -> Task:
        if task.name in self.stats:
            raise ValueError(f"duplicate task name {task.name!r}")
        self.tasks.append(task)
        self.stats[task.name] = TaskStats(task.name, task.divisor * self.base_period_ns / 1e9)
        if self._recorder is not None:
            self._timing_topics[task.name] = self._recorder.topic(
                f"/loop/{task.name}/timing", TIMING_SCHEMA, high_rate=True
            )
        return task

    def add_component(self, component: SafeStateful) -> None:
        """Register something (a driver, an emulator) whose ``safe_state`` must run at stop."""
        self.components.append(component)

    def stop(self, reason: str = "requested") -> None:
        """Ask the loop to stop at the next tick boundary (thread- and signal-safe)."""
        if self.stop_reason is None:
            self.stop_reason = reason
        self._stop.set()

    # -- running -------------------------------------------------------------------------
    def run(self, duration_s: float | None = None, max_ticks: int | None = None) -> None:
        """Run until ``duration_s`` of clock time, ``max_ticks`` base ticks, or a stop request."""
        limit = max_ticks
        if duration_s is not None:
            by_time = round(duration_s * 1e9 / self.base_period_ns)
            limit = by_time if limit is None else min(limit, by_time)
        previous_handlers = self._install_signal_handlers()
        previous_switch = sys.getswitchinterval()
        if self.clock.mode == "realtime":
            # a writer thread holding the GIL for the default 5 ms would wreck a 2 kHz loop
            sys.setswitchinterval(min(previous_switch, REALTIME_SWITCH_INTERVAL_S))
        try:
            self._run_ticks(limit)
        except BaseException as exc:
            self.stop(f"error: {type(exc).__name__}: {exc}")
            raise
        finally:
            sys.setswitchinterval(previous_switch)
            self._restore_signal_handlers(previous_handlers)
            self.safe_state_all()
            self._publish_windows(final=True)
            if self.stop_reason is None:
                self.stop_reason = "completed"

    def _run_ticks(self, limit: int | None) -> None:
        clock, period = self.clock, self.base_period_ns
        windows = {t.name: _Window() for t in self.tasks}
        self._windows = windows
        t0 = self.start_ns = clock.start()
        n = 0
        next_window = self._window_ticks
        perf = time.perf_counter_ns
        realtime = clock.mode == "realtime"  # in lockstep, slow compute costs no virtual time
        recorder = self._recorder
        while not self._stop.is_set() and (limit is None or n < limit):
            deadline = t0 + n * period
            late_by = clock.wait_until(deadline)
            if late_by >= period:  # woke up in a later slot: skip to it, count what was lost
                skip = late_by // period
                if limit is not None:
                    skip = min(skip, limit - n)
                self._count_skipped(n, skip, windows)
                n += skip
                if limit is not None and n >= limit:
                    break
                deadline = t0 + n * period
            for task in self.tasks:
                if n % task.divisor:
                    continue
                stats, window = self.stats[task.name], windows[task.name]
                start = clock.time_ns()
                c0 = perf()
                task.write(task.compute(task.read(start), start), start)
                compute_ns = perf() - c0
                window.lateness_us.append((start - deadline) / 1e3)
                window.compute_us.append(compute_ns / 1e3)
                if realtime and compute_ns > task.divisor * period:
                    window.overruns += 1
                if stats.first_start_ns is None:
                    stats.first_start_ns = start
                stats.last_start_ns = start
                stats.runs += 1
            n += 1
            self.ticks = n
            if recorder is not None:
                recorder.flush_if_due()
            if n >= next_window:
                self._publish_windows(final=False)
                next_window = (n // self._window_ticks + 1) * self._window_ticks

    def _count_skipped(self, first: int, count: int, windows: dict[str, _Window]) -> None:
        """Ticks ``first .. first + count - 1`` will not run: count each task's lost runs."""
        if count <= 0:
            return
        self.skipped_ticks += count
        for task in self.tasks:
            d = task.divisor
            runs_skipped = (first + count - 1) // d - (first - 1) // d
            windows[task.name].missed += runs_skipped
        if self._on_event:
            self._on_event(
                "loop.overrun",
                f"skipped {count} tick(s) from tick {first}",
                {"tick": first, "skipped": int(count)},
            )

    def _publish_windows(self, final: bool) -> None:
        windows = getattr(self, "_windows", None)
        if not windows:
            return
        t_ns = self.clock.time_ns()
        for task in self.tasks:
            window = windows[task.name]
            if final and not window.lateness_us and not window.missed:
                continue
            stats = self.stats[task.name]
            stats.lateness.add_many(window.lateness_us)
            stats.compute.add_many(window.compute_us)
            stats.missed += window.missed
            stats.overruns += window.overruns
            topic = self._timing_topics.get(task.name)
            if topic is not None:
                topic.log(
                    t_ns,
                    {
                        "task": task.name,
                        "period_s": stats.period_s,
                        "runs": len(window.lateness_us),
                        "missed": window.missed,
                        "overruns": window.overruns,
                        "lateness_us": window.lateness_us,
                        "compute_us": window.compute_us,
                    },
                )
            windows[task.name] = _Window()

    def safe_state_all(self) -> list[str]:
        """Call every task's and component's ``safe_state`` (reverse order); return failures."""
        failures = []
        for part in [*reversed(self.components), *reversed(self.tasks)]:
            try:
                part.safe_state()
            except Exception as exc:  # a failing hook must not stop the others
                name = getattr(part, "name", type(part).__name__)
                failures.append(f"{name}: {type(exc).__name__}: {exc}")
        if failures and self._on_event:
            self._on_event("safe_state.failed", "; ".join(failures), {"failures": failures})
        return failures

    def summary(self) -> dict[str, Any]:
        """Per-task stats of the run so far, keyed by task name."""
        return {name: s.summary() for name, s in self.stats.items()}

    # -- signals ---------------------------------------------------------------------------
    def _install_signal_handlers(self) -> dict[int, Any]:
        if not self._handle_signals or threading.current_thread() is not threading.main_thread():
            return {}
        previous: dict[int, Any] = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.getsignal(sig)
            signal.signal(sig, self._on_signal)
        return previous

    def _on_signal(self, signum: int, _frame: Any) -> None:
        self.stop(f"signal {signal.Signals(signum).name}")

    @staticmethod
    def _restore_signal_handlers(previous: dict[int, Any]) -> None:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
