"""A session: one clock, one loop, one MCAP file with metadata, config attachment and events."""

from __future__ import annotations

import functools
import json
import platform
import time
from collections.abc import Iterable
from importlib import metadata as importlib_metadata
from typing import Any

from hil.core.clock import Clock
from hil.core.command_line import command_line
from hil.core.loop import FixedRateLoop, Task
from hil.core.realtime import Hardening, helper_metadata
from hil.core.recording.output import OutputClaim, claim_output
from hil.core.recording.recorder import Recorder, RecorderStats, RecordingOptions, Topic

VERSIONED_PACKAGES = (
    "hil", "numpy", "scipy", "pymodbus", "python-can", "canopen", "cvxpy", "highspy", "daqp",
    "filterpy", "mcap", "pyserial",
)


def package_versions(names: Iterable[str] = VERSIONED_PACKAGES) -> dict[str, str]:
    """Installed versions of the packages that shape a session's behaviour."""
    return dict(_installed_versions(tuple(names)))


@functools.cache
def _installed_versions(names: tuple[str, ...]) -> dict[str, str]:
    """:func:`package_versions`, read once a process: each read parses the package's metadata
    file (some 15 ms for the twelve, a third of a short lockstep run's CPU in a process that
    runs many, a sweep's or a test worker's), and the packages a process has imported do not
    change while it runs."""
    versions = {"python": platform.python_version()}
    for name in names:
        try:
            versions[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


class Session:
    """Owns the recorder and the loop of one run; use as a context manager.

    ``config`` is recorded as a metadata record (JSON) and ``config_text`` (the file as the user
    wrote it, TOML) as an attachment. ``kind`` names the scenario (``bench``, ``servo``...).

    The file is written to its claim's staging file (:mod:`hil.core.recording.output`) and put
    at ``path`` when :meth:`run` starts the loop: a session closed before it ran leaves no file,
    and whatever was at ``path`` stays as it was.
    """

    def __init__(
        self,
        path: str,
        clock: Clock,
        base_period_s: float,
        *,
        kind: str,
        config: dict[str, Any] | None = None,
        config_text: str | None = None,
        config_name: str = "config.toml",
        handle_signals: bool = True,
        harden: bool | None = None,
        recording: RecordingOptions | None = None,
        output: OutputClaim | None = None,
        tunable: bool = False,
    ) -> None:
        self.path = path
        recording = recording or RecordingOptions()
        # the file, checked and locked for this session (run_experiment claims it earlier)
        self.output = output or claim_output(recording.first_file(path))
        # real-time hardening of the loop thread (hil.core.realtime); default: in real time
        self.harden = clock.mode == "realtime" if harden is None else harden
        self.hardening: dict[str, str] = {}
        self._hardening: Hardening | None = None  # applied by prepare, undone after the loop
        self.clock = clock
        self.kind = kind
        self.recorder = Recorder(path, wait_when_full=clock.mode == "sim", options=recording,
                                 tunable=tunable, claim=self.output)
        self.loop = FixedRateLoop(
            clock, base_period_s, recorder=self.recorder, on_event=self._loop_event,
            handle_signals=handle_signals,
        )
        self.recorder.metadata("session", {
            "kind": kind,
            "clock": clock.mode,
            "base_period_s": repr(base_period_s),
            "start_wall_time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "argv": json.dumps(command_line()),
        })
        self.recorder.metadata("versions", package_versions())
        self.recorder.metadata("config", {"json": json.dumps(config or {}, default=str)})
        if config_text is not None:
            self.recorder.attachment(config_name, config_text.encode(), "application/toml")
        self.recorder_stats: RecorderStats | None = None
        self._closed = False

    def topic(self, name: str, schema: dict[str, Any], *, encoding: str | None = None,
              high_rate: bool = False) -> Topic:
        """Register a topic (see :meth:`hil.core.recording.recorder.Recorder.topic` for
        encodings)."""
        return self.recorder.topic(name, schema, encoding=encoding, high_rate=high_rate)

    def add_task(self, task: Task) -> Task:
        return self.loop.add_task(task)

    def add_component(self, component: Any) -> None:
        self.loop.add_component(component)

    def event(
        self, kind: str, message: str, level: str = "info", source: str = "", **data: Any
    ) -> None:
        """Record an event stamped with the session clock."""
        self.recorder.event(self.clock.time_ns(), kind, message, level, source, **data)

    def _loop_event(self, kind: str, message: str, data: dict[str, Any]) -> None:
        level = "warning" if kind.startswith("loop.overrun") else "error"
        self.event(kind, message, level=level, source="loop", **data)

    def prepare(self) -> None:
        """What must be done before the devices are enabled, so that no long pause falls
        between the drive's first cycles and the loop's first tick (an EtherCAT drive's
        watch on lost cycles is 100 ms): the writer process started, and the loop thread
        hardened where the session is (mlockall, the collector frozen, SCHED_FIFO, pinned).
        :meth:`run` does what is not done yet; :meth:`close` undoes the hardening."""
        wait_ready = getattr(self.recorder, "wait_ready", None)
        if wait_ready is not None:
            wait_ready()
        if self.harden and self._hardening is None:
            self._hardening = Hardening()
            self._hardening.apply()
            if self._hardening.pinned_cpu is not None:
                self.recorder.keep_off_cpu(self._hardening.pinned_cpu)

    def run(self, duration_s: float | None = None, max_ticks: int | None = None) -> None:
        """Put the session file in place, then run the loop; safe-state hooks run before this
        returns, whatever happens."""
        self.output.start()
        self.event("session.start", f"{self.kind} session started", source="session")
        try:
            self.prepare()
            if self._hardening is not None:
                self._record_hardening(self._hardening)
            self.loop.run(duration_s=duration_s, max_ticks=max_ticks)
        finally:
            self._restore()
            self.event(
                "session.stop", f"stopped: {self.loop.stop_reason}", source="session",
                reason=self.loop.stop_reason, ticks=self.loop.ticks,
                skipped_ticks=self.loop.skipped_ticks,
            )

    def _restore(self) -> None:
        """The loop thread as it was before :meth:`prepare` hardened it."""
        hardening, self._hardening = self._hardening, None
        if hardening is not None:
            hardening.restore()

    def _record_hardening(self, hardening: Hardening) -> None:
        """Each step, granted or refused: metadata ``realtime`` and one event."""
        self.hardening = hardening.as_metadata()
        self.recorder.metadata("realtime", self.hardening)
        for name, steps in helper_metadata().items():  # emulators standing in for hardware
            self.recorder.metadata(name, steps)
        refused = [s.name for s in hardening.steps if not s.granted]
        self.event("realtime.hardening", "real-time hardening: " + "; ".join(
            f"{name} {value}" for name, value in self.hardening.items()),
            level="warning" if refused else "info", source="session",
            granted=[s.name for s in hardening.steps if s.granted], refused=refused)

    @property
    def started(self) -> bool:
        """Whether the loop was started: only then is the session file at its path."""
        return self.output.started

    def close(self, kpis: dict[str, Any] | None = None) -> RecorderStats:
        """Write loop stats and KPIs as metadata and finish the file (summary + index); a
        session that never ran is removed instead (its staging file: nothing else)."""
        if self._closed and self.recorder_stats is not None:
            return self.recorder_stats
        self._closed = True
        self._restore()  # prepared, then refused before the loop ran
        self.recorder.metadata("loop", {
            name: json.dumps(stats) for name, stats in self.loop.summary().items()
        })
        if kpis is not None:
            self.recorder.metadata("kpis", {"json": json.dumps(kpis, default=str)})
        try:
            self.recorder_stats = self.recorder.close()
        finally:
            self.output.abandon()  # the lock goes; the file too if the session never ran
        return self.recorder_stats

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
