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


#: the kernel's budget for real-time threads on a CPU, per period (``sched_rt_runtime_us``
#: of ``sched_rt_period_us``: 950 ms of every second by default, -1 for none)
RT_RUNTIME = "/proc/sys/kernel/sched_rt_runtime_us"
RT_PERIOD = "/proc/sys/kernel/sched_rt_period_us"
RT_HEADROOM = 0.05  # below the kernel's budget: what else runs real-time on the loop's core


def busy_share_max(runtime: str = RT_RUNTIME, period: str = RT_PERIOD) -> float:
    """The share of each cycle the loop's core may be busy (the loop working, then spinning,
    with whatever answers it there): below the kernel's budget for real-time threads, which
    stops them all for the rest of its period once they used it up (throttling: 50 ms of every
    second by default, a hundred 2 kHz ticks at once). 1.0 where the kernel has no budget."""
    try:
        with open(runtime) as runtime_file, open(period) as period_file:
            budget_us, period_us = int(runtime_file.read()), int(period_file.read())
    except (OSError, ValueError):
        return 1.0
    if budget_us < 0 or period_us <= 0:
        return 1.0
    return max(0.0, min(1.0, budget_us / period_us - RT_HEADROOM))


def spin_from(now_ns: int, target_ns: int, woke_ns: int | None, margin_ns: int,
              busy_share: float) -> int:
    """When a wait begun at ``now_ns`` for ``target_ns`` stops sleeping and spins (monotonic
    ns): ``margin_ns`` before the target, or later, so that the cycle since the last wake-up
    at ``woke_ns`` is busy (working until now, then spinning) for at most ``busy_share`` of
    it; with no spin left, at ``target_ns`` (a sleep all the way: a few tens of microseconds
    late)."""
    spin_ns = margin_ns
    if woke_ns is not None and busy_share < 1.0:
        allowed = round(busy_share * (target_ns - woke_ns)) - (now_ns - woke_ns)
        spin_ns = min(spin_ns, max(0, allowed))
    return target_ns - spin_ns


class RealtimeClock:
    """Absolute deadlines on ``time.monotonic_ns``: sleep until ``spin_margin_ns`` before the
    deadline, then spin (yielding the GIL) until it passes.

    Sleeping alone wakes up 50 us to 1 ms late on a loaded Linux box; the final spin trades a
    little CPU for a wake-up within a few microseconds of the deadline. A spin never keeps the
    core busy for more than ``busy_share`` of a cycle (:func:`spin_from`; by default below the
    kernel's budget for real-time threads, :func:`busy_share_max`): a hardened loop whose
    ticks take most of the period would otherwise use up that budget, and the kernel would
    stop it for 50 ms of every second.
    """

    mode = "realtime"

    def __init__(self, spin_margin_ns: int = 200_000, busy_share: float | None = None) -> None:
        if spin_margin_ns < 0:
            raise ValueError("spin_margin_ns must be >= 0")
        self.spin_margin_ns = spin_margin_ns
        self.busy_share = busy_share_max() if busy_share is None else busy_share
        self._woke: int | None = None  # the end of the last wait (monotonic ns)
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
        now = time.monotonic_ns()
        spin = spin_from(now, target, self._woke, self.spin_margin_ns, self.busy_share)
        if spin > now:
            time.sleep((spin - now) / 1e9)
            now = time.monotonic_ns()
        while now < target:
            os.sched_yield()  # releases the GIL (time.sleep(0) would hit the 50 us timer slack)
            now = time.monotonic_ns()
        self._woke = now
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
