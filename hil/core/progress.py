"""A progress line on the terminal while a run goes: session time done out of the planned,
refreshed about once a second of wall time, on stderr, only when stderr is a terminal (a
pipe, a log file or CI gets nothing), never with ``--quiet``.

The loop's thread only notes how far the run is (a store, every ``divisor`` ticks); a thread
of its own writes the line, so a terminal that is slow to take it (a remote session, a paused
output) never holds up a tick.
"""

from __future__ import annotations

import sys
import threading
from typing import TextIO

from hil.core.loop import Task
from hil.core.realtime import ordinary_thread

REFRESH_S = 1.0


class ProgressLine(Task):
    """Record phase, every ``divisor`` ticks: note the session time; a writer thread (started
    here, before any real-time hardening of the loop's thread) rewrites the line once a
    second until :meth:`clear`."""

    def __init__(self, label: str, duration_s: float, divisor: int,
                 stream: TextIO | None = None) -> None:
        super().__init__("progress", divisor)
        self.label, self.duration_s = label, duration_s
        self.stream = stream or sys.stderr
        self._t0_ns: int | None = None
        self._t_ns: int | None = None  # the last tick noted (a plain store: the loop's part)
        self._stop = threading.Event()
        self.shown = False
        self._writer = threading.Thread(target=self._write_every_second, name="progress",
                                        daemon=True)
        self._writer.start()

    def record(self, t_ns: int) -> None:
        if self._t0_ns is None:
            self._t0_ns = t_ns
        self._t_ns = t_ns

    def _write_every_second(self) -> None:
        ordinary_thread()
        while not self._stop.wait(REFRESH_S):
            t0, t = self._t0_ns, self._t_ns
            if t0 is None or t is None:
                continue
            done = (t - t0) / 1e9
            share = min(1.0, done / self.duration_s) if self.duration_s else 1.0
            self.stream.write(f"\r{self.label}: {done:.1f} of {self.duration_s:g} s "
                              f"({share:.0%})\x1b[K")
            self.stream.flush()
            self.shown = True

    def clear(self) -> None:
        """Stop the writer and take the line away (the run's own output follows)."""
        self._stop.set()
        self._writer.join()
        if self.shown:
            self.stream.write("\r\x1b[K")
            self.stream.flush()


def wants_progress(quiet: bool, stream: TextIO | None = None) -> bool:
    """Whether to show progress: not ``quiet`` and ``stream`` (stderr) is a terminal."""
    stream = stream or sys.stderr
    return not quiet and hasattr(stream, "isatty") and stream.isatty()
