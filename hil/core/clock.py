"""Clocks that drive the loop: real time on the monotonic clock, or lockstep virtual time.

Both expose time in integer nanoseconds. ``time_ns()`` is the session time stamped on every
recorded message: for :class:`RealtimeClock` it is wall-clock epoch time advanced by the
monotonic clock (so files line up with the outside world and never jump), for :class:`SimClock`
it starts at 0 and advances only when the loop asks for the next deadline.
"""

from __future__ import annotations

import os
import time
from typing import Protocol


class Clock(Protocol):
    """What the loop needs from a clock."""

    mode: str

    def start(self) -> int:
        """Start (or restart) the clock; return the current time in ns."""
        ...

    def time_ns(self) -> int:
        """Current session time in ns."""
        ...

    def wait_until(self, deadline_ns: int) -> int:
        """Block until ``deadline_ns``; return the lateness of the wake-up in ns (>= 0)."""
        ...


class RealtimeClock:
    """Absolute deadlines on ``time.monotonic_ns``: sleep until ``spin_margin_ns`` before the
    deadline, then spin (yielding the GIL) until it passes.

    Sleeping alone wakes up 50 us to 1 ms late on a loaded Linux box; the final spin trades a
    little CPU for a wake-up within a few microseconds of the deadline.
    """

    mode = "realtime"

    def __init__(self, spin_margin_ns: int = 200_000) -> None:
        if spin_margin_ns < 0:
            raise ValueError("spin_margin_ns must be >= 0")
        self.spin_margin_ns = spin_margin_ns
        self._mono0 = time.monotonic_ns()
        self._epoch0 = time.time_ns()

    def start(self) -> int:
        self._mono0 = time.monotonic_ns()
        self._epoch0 = time.time_ns()
        return self._epoch0

    def time_ns(self) -> int:
        return self._epoch0 + (time.monotonic_ns() - self._mono0)

    def wait_until(self, deadline_ns: int) -> int:
        target = deadline_ns - self._epoch0 + self._mono0
        remaining = target - time.monotonic_ns()
        if remaining > self.spin_margin_ns:
            time.sleep((remaining - self.spin_margin_ns) / 1e9)
        now = time.monotonic_ns()
        while now < target:
            os.sched_yield()  # releases the GIL (time.sleep(0) would hit the 50 us timer slack)
            now = time.monotonic_ns()
        return now - target


class SimClock:
    """Lockstep virtual time: waiting jumps to the deadline. Deterministic, never sleeps."""

    mode = "sim"

    def __init__(self, start_ns: int = 0) -> None:
        self._start_ns = start_ns
        self._now_ns = start_ns

    def start(self) -> int:
        self._now_ns = self._start_ns
        return self._now_ns

    def time_ns(self) -> int:
        return self._now_ns

    def wait_until(self, deadline_ns: int) -> int:
        if deadline_ns > self._now_ns:
            self._now_ns = deadline_ns
        return 0
