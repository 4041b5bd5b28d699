"""Value types and contracts shared by every layer: the only part of hil (with
:mod:`hil.errors`) that drivers, emulators and controllers may import.

* :class:`TimeSource` - what a device needs of the loop's clock (session time in ns).
* :data:`EventSink` - where a device reports what happened (``Session.event``'s signature).
* :class:`LinkWatchdog` - "N failures in a row, then the link is lost": one rule for the relay
  bench (failed Modbus polls) and the servo drive (cycles without a TPDO).
* :class:`PollBudget` - how long a wait for a peer on the wire polls before it blocks, while
  polling pays: one rule for a lockstep master waiting for the drive's answer and the emulated
  drive waiting for the master's next SYNC.
* :class:`Device` - the lifecycle every piece of hardware goes through, in the spirit of
  ros2_control's hardware interface: open -> configure -> enable -> ... -> safe_state -> close.
"""

from __future__ import annotations

import abc
import contextlib
import os
from collections.abc import Callable
from typing import Any, Protocol

from hil.errors import ConfigError, HilError


class TimeSource(Protocol):
    """A clock as devices see it: the session time (simulated in lockstep, wall in real time)."""

    def time_ns(self) -> int:
        """Current session time in ns."""
        ...


EventSink = Callable[..., None]
"""``(kind, message, level="info", source=..., **data)``: records one event (``/events``)."""


def no_event(kind: str, message: str, **data: Any) -> None:
    """An :data:`EventSink` that drops everything (a device used outside a session)."""
    return None


class LinkWatchdog:
    """Declares a link lost after ``limit`` failures in a row; one success restores it.

    A failure is whatever the device counts: a failed poll of the bench, a cycle without the
    drive's feedback. ``failure()`` answers True exactly once per loss, so the caller reacts
    (event, safe state) once.
    """

    def __init__(self, limit: int, what: str = "failures") -> None:
        if limit < 1:
            raise ConfigError(f"watchdog: the number of {what} that declare a link lost must be "
                              f">= 1, got {limit}")
        self.limit = limit
        self.what = what
        self.run = 0           # failures in a row now
        self.longest_run = 0   # longest run of failures seen
        self.lost = False
        self.losses = 0        # times the link was declared lost

    def failure(self) -> bool:
        """Count one failure; True when this one declares the link lost."""
        self.run += 1
        self.longest_run = max(self.longest_run, self.run)
        if not self.lost and self.run >= self.limit:
            self.lost = True
            self.losses += 1
            return True
        return False

    def success(self) -> None:
        """A good exchange: the run of failures ends and the link is up."""
        self.run = 0
        self.lost = False

    def describe(self) -> str:
        """``"5 failed polls in a row"``: the reason of a loss, for events and errors."""
        return f"{self.run} {self.what} in a row"


#: Linux's pressure stall information for the CPUs (kernels 4.20 and later)
CPU_PRESSURE = "/proc/pressure/cpu"
#: a machine whose tasks waited for a CPU over this share (%) of the last 10 s is contended
CONTENDED_PRESSURE = 10.0


def cpu_contended(pressure: str = CPU_PRESSURE,
                  load: Callable[[], tuple[float, float, float]] = os.getloadavg) -> bool:
    """Whether this machine's CPUs are oversubscribed: some runnable task waited for one over
    :data:`CONTENDED_PRESSURE` % of the last 10 s (``pressure``'s ``some avg10``) or, where the
    kernel has no such file, the 1-minute ``load`` average is over the usable cores plus one
    (where there is neither: not contended)."""
    try:
        with open(pressure, "rb") as stalls:
            some = stalls.readline().split()  # b"some avg10=17.82 avg60=56.35 ..."
        return float(some[1].removeprefix(b"avg10=")) > CONTENDED_PRESSURE
    except (OSError, ValueError, IndexError):
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") \
        else os.cpu_count() or 1
    try:
        return load()[0] > cores + 1
    except OSError:
        return False


class PollBudget:
    """How long a wait for a peer polls before it blocks, while polling pays.

    A process blocked in ``select()`` is woken up 50 us to several hundred us after the data
    arrives (more on a virtual machine, whose idle core must be woken first), where a look
    that finds it costs a few: a wait that polls for the first ``window_ns`` answers a peer
    that is quick at once. It pays only on a core of its own: on a busy machine a process
    that polls keeps others (the very peer it waits for, on a core they share) from running,
    and a blocked one is woken up first. A look that comes ``preempted_ns`` or more after the
    one before it (the process was off the CPU) ends the wait's polling; after ``strikes``
    such waits with no clean one between, the waits of the next ``backoff_ns`` block from their
    start (one other process's burst, a session's writer, is not a busy machine). Nor do they
    poll for ``backoff_ns`` while the machine is ``contended()`` (:func:`cpu_contended`, asked
    at most once per ``backoff_ns``): where tasks already wait for a CPU, polling takes one
    from them. :meth:`start` a wait, then ask :meth:`polling` before each look.
    """

    def __init__(self, window_ns: int, *, preempted_ns: int = 200_000, strikes: int = 3,
                 backoff_ns: int = 100_000_000,
                 contended: Callable[[], bool] = cpu_contended) -> None:
        self.window_ns = window_ns
        self.preempted_ns = preempted_ns
        self.strikes = strikes
        self.backoff_ns = backoff_ns
        self._until = 0          # this wait polls until then
        self._last = 0           # the last look
        self._preempted = False  # this wait was
        self._struck = 0         # preempted waits since the last clean one
        self._calm_from = 0      # no polling before then
        self.contended = contended
        self._machine_due = 0    # when contended() is asked next
        self.backoffs = 0        # times the waits stopped polling for backoff_ns

    def start(self, now_ns: int) -> None:
        """A wait begins (monotonic or perf-counter ns, the same clock throughout)."""
        if not self._preempted:
            self._struck = 0
        self._preempted = False
        if now_ns >= self._machine_due:
            self._machine_due = now_ns + self.backoff_ns
            if self.contended():
                self._calm_from = now_ns + self.backoff_ns
        self._until = now_ns + self.window_ns if now_ns >= self._calm_from else now_ns
        self._last = now_ns

    def polling(self, now_ns: int) -> bool:
        """Whether to look without blocking now: within the window, and not preempted since
        the last look (which ends this wait's polling)."""
        if now_ns >= self._until:
            return False
        if now_ns - self._last >= self.preempted_ns:
            self._until, self._preempted = now_ns, True
            self._struck += 1
            if self._struck >= self.strikes:
                self._struck, self._calm_from = 0, now_ns + self.backoff_ns
                self.backoffs += 1
            return False
        self._last = now_ns
        return True


class Device(abc.ABC):
    """The contract of a piece of hardware behind a link (bench, drive, or a user's device).

    Lifecycle, each step explicit (ros2_control's configure/activate/deactivate/error):

    * ``open()`` - reach the device and leave it in its safe state (relays at their safe
      level, drive disabled). Raises a :class:`~hil.errors.HilError` naming the device
      when it cannot.
    * ``configure()`` - write the settings the run needs (PDO maps, periods, limits).
    * ``enable()`` - make it follow commands (drive: OPERATION ENABLED). Default: nothing to do.
    * ``safe_state()`` - outputs to their safe state whatever the controller asked; idempotent.
      The loop calls it on every stop, error or Ctrl-C, and the device calls it on a lost link.
    * ``close()`` - safe state (best effort), then release the link; idempotent.

    ``link_up`` reads the device's :class:`LinkWatchdog`. Devices are context managers whose
    exit closes them.
    """

    watchdog: LinkWatchdog

    @property
    @abc.abstractmethod
    def url(self) -> str:
        """Where the device is (``modbus-tcp://...``, ``socketcand://...``, ``emulated``)."""

    @property
    def link_up(self) -> bool:
        return not self.watchdog.lost

    @abc.abstractmethod
    def open(self) -> None:
        """Reach the device and leave it in its safe state."""

    def configure(self) -> None:
        """Write the settings the run needs. Default: none."""
        return None

    def enable(self) -> None:
        """Make the device follow commands. Default: it always does."""
        return None

    @abc.abstractmethod
    def safe_state(self) -> None:
        """Outputs to their safe state; idempotent."""

    @abc.abstractmethod
    def disconnect(self) -> None:
        """Release the link (sockets, serial port, bus); idempotent."""

    def close(self) -> None:
        """Safe state (best effort: the link may be gone), then release the link."""
        try:
            with contextlib.suppress(HilError):
                self.safe_state()
        finally:
            self.disconnect()

    def __enter__(self) -> Device:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
