"""FixedRateLoop: one base period, tasks every ``divisor`` ticks, each tick in four phases.

Each tick runs the **read** phase of every task that is due (devices in), then every
**compute** (controllers), every **write** (devices out), every **record** (topics, KPIs,
limits): ros2_control's read -> update -> write, plus recording. A task takes part in the
phases it overrides; what one phase leaves for the next stays on the task (or on an object
the tasks share), so data flows one way: the feedback read in tick k is computed on and
written in tick k. Each phase of each task is timed under its own name (``read_us``,
``compute_us``, ``write_us``, ``record_us``); ``tick_us`` is their sum.

Overrun policy: when the loop wakes up one or more whole base periods after a tick's deadline,
the ticks whose slots have passed are skipped and counted (per task, as ``missed``); the
schedule stays on its absolute grid, so the loop never drifts. In real time, a task whose
phases take longer than its own period is counted in ``overruns`` (in lockstep, compute time
is reported but costs no virtual time). SIGINT/SIGTERM stop the loop at the next tick
boundary; every component's ``safe_state()`` runs before :meth:`FixedRateLoop.run` returns,
also on errors.

No tick does a period's worth of bookkeeping. Each run's samples (lateness, phase times) are
binned into the run's histograms as they are taken (:meth:`TimingHistogram.add`: the same
small work each tick) and handed to the recorder as one row
(:class:`~hil.core.recording.recorder.ColumnTopic`): the writer builds the window's timing
record (about once a second) from the rows, so its close hands over no samples. Work left
whole for every N ticks costs one tick the work of N: at 2 kHz, a window binned and pickled in
one tick was a skipped tick every second; binned 512 samples a tick by numpy (some 40 us a
call, whatever its size) and handed over as five buffers at once (100-300 us), it still made
the ticks after each whole second late, with skips among them.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from array import array
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

from hil.core.clock import Clock
from hil.core.stats import TimingHistogram

# While a real-time loop runs, another thread holding the GIL is forced to hand it over after
# this long (CPython's default is 5 ms: ten 2 kHz ticks lost behind the recorder's writer).
REALTIME_SWITCH_INTERVAL_S = 1e-4

#: the phases of a tick, in the order they run
PHASES = ("read", "compute", "write", "record")

class SafeStateful(Protocol):
    def safe_state(self) -> None: ...


class Task:
    """One job of the loop. Subclass and override the phases it takes part in (all optional).

    ``read`` takes in what a device reports, ``compute`` runs a controller, ``write`` sends
    to a device, ``record`` logs the tick (topics, KPIs, per-tick limits). Every phase gets
    the tick's start time (clock ns). ``prime`` runs once before the clock starts (a first
    exchange with a device, outside the schedule). ``safe_state`` puts whatever this task
    drives into its safe state; it must be idempotent.
    """

    def __init__(self, name: str, divisor: int = 1) -> None:
        if not name or "/" in name:
            raise ValueError(f"task name must be non-empty without '/': {name!r}")
        if int(divisor) != divisor or divisor < 1:
            raise ValueError(f"task {name!r}: divisor must be a positive integer, got {divisor!r}")
        self.name = name
        self.divisor = int(divisor)

    @property
    def phases(self) -> tuple[str, ...]:
        """The phases this task takes part in: those its class overrides."""
        return tuple(p for p in PHASES if getattr(type(self), p) is not getattr(Task, p))

    def prime(self) -> None:
        """Once, after the loop is set up and right before its clock starts (untimed): a
        device's first answer, which comes late (a peer that has not been asked yet, caches
        cold), waited for here rather than in the first ticks."""
        return None

    def read(self, t_ns: int) -> None:
        return None

    def compute(self, t_ns: int) -> None:
        return None

    def write(self, t_ns: int) -> None:
        return None

    def record(self, t_ns: int) -> None:
        return None

    def safe_state(self) -> None:
        return None


class FunctionTask(Task):
    """A task made of plain callables ``f(t_ns)``, one per phase, for small jobs and tests."""

    def __init__(
        self,
        name: str,
        divisor: int = 1,
        *,
        read: Callable[[int], None] | None = None,
        compute: Callable[[int], None] | None = None,
        write: Callable[[int], None] | None = None,
        record: Callable[[int], None] | None = None,
        safe_state: Callable[[], None] | None = None,
    ) -> None:
        super().__init__(name, divisor)
        self._calls = {"read": read, "compute": compute, "write": write, "record": record}
        self._safe = safe_state

    @property
    def phases(self) -> tuple[str, ...]:
        return tuple(p for p in PHASES if self._calls[p] is not None)

    def read(self, t_ns: int) -> None:
        self._run("read", t_ns)

    def compute(self, t_ns: int) -> None:
        self._run("compute", t_ns)

    def write(self, t_ns: int) -> None:
        self._run("write", t_ns)

    def record(self, t_ns: int) -> None:
        self._run("record", t_ns)

    def _run(self, phase: str, t_ns: int) -> None:
        call = self._calls[phase]
        if call is not None:
            call(t_ns)

    def safe_state(self) -> None:
        if self._safe:
            self._safe()


@dataclass
class TaskStats:
    """Timing of one task over a whole run (lateness and phase times in us)."""

    name: str
    period_s: float
    phases: tuple[str, ...] = ()
    runs: int = 0
    missed: int = 0
    overruns: int = 0
    lateness: TimingHistogram = field(default_factory=TimingHistogram)
    step: TimingHistogram = field(default_factory=TimingHistogram)
    phase_times: dict[str, TimingHistogram] = field(default_factory=dict)
    first_start_ns: int | None = None
    last_start_ns: int | None = None

    def __post_init__(self) -> None:
        self.phase_times = {phase: TimingHistogram() for phase in self.phases}

    def measured_period_s(self) -> float:
        if self.runs < 2 or self.first_start_ns is None or self.last_start_ns is None:
            return 0.0
        return (self.last_start_ns - self.first_start_ns) / (self.runs - 1) / 1e9

    def summary(self) -> dict[str, Any]:
        """Counts, lateness, ``tick_us`` (all phases) and ``<phase>_us`` of each phase run."""
        summary: dict[str, Any] = {
            "period_s": self.period_s,
            "measured_period_s": round(self.measured_period_s(), 9),
            "runs": self.runs,
            "missed": self.missed,
            "overruns": self.overruns,
            "lateness_us": self.lateness.summary(),
            "tick_us": self.step.summary(),
        }
        for phase, histogram in self.phase_times.items():
            summary[f"{phase}_us"] = histogram.summary()
        return summary


class _Window:
    """One task's counts since its last timing record (its samples went to the recorder as
    rows)."""

    __slots__ = ("missed", "overruns", "runs")

    def __init__(self) -> None:
        self.runs = 0
        self.missed = 0
        self.overruns = 0


_TIMES = {"type": "array", "items": {"type": "number", "x-cdr": "float32"}}
TIMING_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.LoopTiming",
    "description": "Per-task timing of the fixed-rate loop over one window (about 1 s): "
                   "lateness of each run and the time of each phase the task takes part in "
                   "(empty for the others).",
    "properties": {
        "task": {"type": "string"},
        "period_s": {"type": "number"},
        "runs": {"type": "integer"},
        "missed": {"type": "integer", "description": "scheduled runs skipped in this window"},
        "overruns": {"type": "integer", "description": "runs longer than the task period"},
        "lateness_us": _TIMES,
        "read_us": _TIMES,
        "compute_us": _TIMES,
        "write_us": _TIMES,
        "record_us": _TIMES,
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
        #: each task's timing record, built in the writer a row a tick (recorder.ColumnTopic)
        self._timing_columns: dict[str, Any] = {}
        self._on_event = on_event
        self._window_ticks = max(1, round(stats_window_s * 1e9 / self.base_period_ns))
        self._handle_signals = handle_signals
        self._stop = threading.Event()
        self._signalled = False  # set by the signal handler: a plain store, nothing that locks
        self.stop_reason: str | None = None
        self.ticks = 0
        #: the number of the tick whose phases run now, its slot on the schedule grid (a
        #: tick that starts late, even by nearly a period, keeps its slot's number)
        self.tick_number = 0
        self.skipped_ticks = 0
        self.ticking_s = 0.0  # wall time from the first tick to the end of the last
        self.start_ns = 0  # clock time of tick 0's deadline: the origin of the schedule grid
        #: called with the tick's number at each tick boundary, before its phases (the run's
        #: tuner applies parameter changes there); None: nothing
        self.at_boundary: Callable[[int], None] | None = None
        for task in tasks:
            self.add_task(task)

    # -- configuration -------------------------------------------------------------------
    def add_task(self, task: Task) -> Task:
        if task.name in self.stats:
            raise ValueError(f"duplicate task name {task.name!r}")
        self.tasks.append(task)
        self.stats[task.name] = TaskStats(task.name, task.divisor * self.base_period_ns / 1e9,
                                          task.phases)
        if self._recorder is not None:
            self._timing_columns[task.name] = self._recorder.columns(self._recorder.topic(
                f"/loop/{task.name}/timing", TIMING_SCHEMA, high_rate=True))
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
            wait_ready = getattr(self._recorder, "wait_ready", None)
            if wait_ready is not None:  # a recorder's writer process: started before tick 0
                wait_ready()
            for task in self.tasks:
                task.prime()
            if self._recorder is not None:  # what set-up logged (topics...) goes before tick 0
                self._recorder.flush()
            began = time.perf_counter()
            try:
                self._run_ticks(limit)
            finally:
                self.ticking_s = time.perf_counter() - began
        except BaseException as exc:
            self.stop(f"error: {type(exc).__name__}: {exc}")
            raise
        finally:
            sys.setswitchinterval(previous_switch)
            try:  # a signal during the safe state is one more stop request, not a kill
                self.safe_state_all()
                self._publish_windows(final=True)
            finally:
                self._restore_signal_handlers(previous_handlers)
            if self.stop_reason is None:
                self.stop_reason = "completed"

    def _run_ticks(self, limit: int | None) -> None:
        clock, period = self.clock, self.base_period_ns
        tasks = self.tasks
        windows = {t.name: _Window() for t in tasks}
        self._windows = windows
        # each task's row of this tick: its lateness, then each of its phases' times (us)
        rows = [[0.0] * (1 + len(task.phases)) for task in tasks]
        schedule, slots = self._schedule(rows), self._slots(windows, rows)
        spent = [0] * len(tasks)  # ns each task spent in this tick's phases
        t0 = self.start_ns = clock.start()
        n = 0
        next_window = self._window_ticks
        perf = time.perf_counter_ns
        realtime = clock.mode == "realtime"  # in lockstep, slow compute costs no virtual time
        recorder = self._recorder
        boundary = self.at_boundary
        while not (self._signalled or self._stop.is_set()) and (limit is None or n < limit):
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
            self.tick_number = n
            if boundary is not None:
                boundary(n)
            start = clock.time_ns()
            for index, divisor, method, bin_time, row, at in schedule:
                if n % divisor:
                    continue
                c0 = perf()
                method(start)
                elapsed = perf() - c0
                row[at] = us = elapsed / 1e3
                bin_time(us)
                spent[index] += elapsed
            lateness_us = (start - deadline) / 1e3
            for index, divisor, window, stats, columns, row in slots:
                if n % divisor:
                    continue
                stats.lateness.add(lateness_us)
                stats.step.add(spent[index] / 1e3)
                window.runs += 1
                if columns is not None:  # this run's row of the window's timing record
                    row[0] = lateness_us
                    columns.add(tuple(row))
                if realtime and spent[index] > divisor * period:
                    window.overruns += 1
                spent[index] = 0
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
                slots = self._slots(windows, rows)  # the new windows
                next_window = (n // self._window_ticks + 1) * self._window_ticks

    def _schedule(self, rows: list[list[float]]) -> list[tuple[
            int, int, Callable[[int], None], Callable[[float], None], list[float], int]]:
        """Every phase method of a tick, in order (phase by phase, then in the order the
        tasks were added): ``(task index, divisor, bound phase method, what bins its time,
        the task's row, the time's place in it)``."""
        return [(index, task.divisor, getattr(task, phase),
                 self.stats[task.name].phase_times[phase].add, rows[index],
                 1 + task.phases.index(phase))
                for phase in PHASES
                for index, task in enumerate(self.tasks) if phase in task.phases]

    def _slots(self, windows: dict[str, _Window], rows: list[list[float]]) -> list[tuple[
            int, int, _Window, TaskStats, Any, list[float]]]:
        """Per task, for the end of a tick: ``(index, divisor, its window, its stats, its
        timing record's columns or None, its row)``."""
        return [(index, task.divisor, windows[task.name], self.stats[task.name],
                 self._timing_columns.get(task.name), rows[index])
                for index, task in enumerate(self.tasks)]

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
        """Each task's window as its timing record (its columns: the rows handed over each
        tick) and a new window: the same work for a window of any length."""
        windows = getattr(self, "_windows", None)
        if not windows:
            return
        t_ns = self.clock.time_ns()
        for task in self.tasks:
            window = windows[task.name]
            if final and not window.runs and not window.missed:
                continue
            stats = self.stats[task.name]
            stats.missed += window.missed
            stats.overruns += window.overruns
            columns = self._timing_columns.get(task.name)
            if columns is not None:
                fields: dict[str, Any] = {
                    "task": task.name,
                    "period_s": stats.period_s,
                    "runs": window.runs,
                    "missed": window.missed,
                    "overruns": window.overruns,
                    **{f"{phase}_us": array("d") for phase in PHASES
                       if phase not in task.phases},
                }
                columns.log(t_ns, fields, ("lateness_us", *(f"{p}_us" for p in task.phases)))
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
        """Plain stores only: ``Event.set()`` takes a lock the interrupted code may hold (two
        signals a few ms apart would then deadlock the main thread)."""
        if self.stop_reason is None:
            self.stop_reason = f"signal {signal.Signals(signum).name}"
        self._signalled = True

    def _restore_signal_handlers(self, previous: dict[int, Any]) -> None:
        """The handlers from before :meth:`run`; after a signal stopped the loop, a SIGTERM
        that would kill the process is ignored instead: the process is on its way out, and a
        repeat (a supervisor's retry, ms later) must not cut off its session file."""
        for sig, handler in previous.items():
            if self._signalled and sig == signal.SIGTERM and handler == signal.SIG_DFL:
                handler = signal.SIG_IGN
            signal.signal(sig, handler)
