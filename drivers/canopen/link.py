"""The master's side of the bus: CAN frames as ``(id, data)`` tuples, sent in one call per
cycle, received with a deadline, every one also handed to a trace (``--can-log``) if any.

Bus errors become :class:`~drivers.canopen.errors.DriveLinkLostError` naming the bus.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Protocol

import can

from drivers.can_frames import Frame, frames_of
from drivers.canopen.errors import DriveLinkLostError, one_line


class FrameTrace(Protocol):
    """Where a copy of every frame goes (:class:`drivers.canopen.can_log.CanLog`)."""

    def sent(self, frames: list[Frame]) -> None: ...

    def received(self, frame: Frame) -> None: ...


class CanLink:
    """One bus as the master uses it; ``reopen`` builds the bus again after a lost link."""

    def __init__(self, bus: can.BusABC, *, reopen: Callable[[], can.BusABC] | None = None,
                 trace: FrameTrace | None = None) -> None:
        self.reopen = reopen
        self.trace = trace
        self._use(bus)

    def _use(self, bus: can.BusABC) -> None:
        self.bus = bus
        frames = frames_of(bus)
        self._send_frames, self._recv_frame = frames.send_frames, frames.recv_frame

    @property
    def name(self) -> str:
        return str(self.bus.channel_info)

    def send(self, frames: list[Frame]) -> None:
        """``frames`` in this order, in one transmission where the transport allows."""
        try:
            self._send_frames(frames)
        except (can.CanError, OSError) as exc:
            raise DriveLinkLostError(f"cannot send on {self.name}: {self._detail(exc)}") from None
        if self.trace is not None:
            self.trace.sent(frames)

    def recv(self, timeout: float | None) -> Frame | None:
        """The next frame within ``timeout`` seconds (0: only one already here), or None."""
        try:
            frame = self._recv_frame(timeout)
        except (can.CanError, OSError) as exc:
            raise DriveLinkLostError(f"cannot read {self.name}: {self._detail(exc)}") from None
        if frame is not None and self.trace is not None:
            self.trace.received(frame)
        return frame

    def _detail(self, exc: BaseException) -> str:
        """The bus error's message without the bus name it may start with (ours names it)."""
        detail = one_line(exc)
        return detail.removeprefix(f"{self.name}: ")

    def reconnect(self) -> None:
        """The bus built again (after a lost link), when the master was given the way."""
        if self.reopen is None:
            return
        with contextlib.suppress(Exception):  # the old connection is gone anyway
            self.bus.shutdown()
        self._use(self.reopen())

    def shutdown(self) -> None:
        self.bus.shutdown()
