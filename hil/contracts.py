"""Value types and contracts shared by every layer: the only part of hil (with
:mod:`hil.errors`) that drivers, emulators and controllers may import.

* :class:`TimeSource` - what a device needs of the loop's clock (session time in ns).
* :data:`EventSink` - where a device reports what happened (``Session.event``'s signature).
* :class:`LinkWatchdog` - "N failures in a row, then the link is lost": one rule for the relay
  bench (failed Modbus polls) and the servo drive (cycles without a TPDO).
* :class:`Device` - the lifecycle every piece of hardware goes through, in the spirit of
  ros2_control's hardware interface: open -> configure -> enable -> ... -> safe_state -> close.
"""

from __future__ import annotations

import abc
import contextlib
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
