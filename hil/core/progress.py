"""A progress line on the terminal while a run goes: session time done out of the planned,
refreshed about once a second of wall time, on stderr, only when stderr is a terminal (a
pipe, a log file or CI gets nothing), never with ``--quiet``."""

from __future__ import annotations

import sys
import time
from typing import TextIO

from hil.core.loop import Task

REFRESH_S = 1.0


class ProgressLine(Task):
    """Record phase, every ``divisor`` ticks: rewrite the line when a second has passed."""

    def __init__(self, label: str, duration_s: float, divisor: int,
                 stream: TextIO | None = None) -> None:
        super().__init__("progress", divisor)
        self.label, self.duration_s = label, duration_s
        self.stream = stream or sys.stderr
        self._t0_ns: int | None = None
        self._next = time.monotonic() + REFRESH_S
        self.shown = False

    def record(self, t_ns: int) -> None:
        if self._t0_ns is None:
            self._t0_ns = t_ns
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + REFRESH_S
        done = (t_ns - self._t0_ns) / 1e9
        share = min(1.0, done / self.duration_s) if self.duration_s else 1.0
        self.stream.write(f"\r{self.label}: {done:.1f} of {self.duration_s:g} s "
                          f"({share:.0%})\x1b[K")
        self.stream.flush()
        self.shown = True

    def clear(self) -> None:
        """Take the line away (the run's own output follows)."""
        if self.shown:
            self.stream.write("\r\x1b[K")
            self.stream.flush()


def wants_progress(quiet: bool, stream: TextIO | None = None) -> bool:
    """Whether to show progress: not ``quiet`` and ``stream`` (stderr) is a terminal."""
    stream = stream or sys.stderr
    return not quiet and hasattr(stream, "isatty") and stream.isatty()
