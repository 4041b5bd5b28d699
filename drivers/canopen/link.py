"""The master's side of the bus: CAN frames as ``(id, data)`` tuples, sent in one call per
cycle, received with a deadline, every one also handed to a trace (``--can-log``) if any.

Bus errors become :class:`~drivers.canopen.errors.DriveLinkLostError` naming the bus.
"""

from __future__ import annotations

import contextlib
import time
from collections import deque
from collections.abc import Callable
from typing import Protocol

import can

from drivers.can_frames import Frame, frames_of
from drivers.canopen.errors import DriveLinkLostError, one_line

OWN_ECHO_WINDOW_NS = 100_000_000  # a bus that echoes does so within milliseconds
OWN_FRAMES_KEPT = 256
#: python-can buses that hand a sender its own frames back (multicast loopback)
ECHOING_BUS_MODULES = ("can.interfaces.udp_multicast",)


class FrameTrace(Protocol):
    """Where a copy of every frame goes (:class:`drivers.canopen.can_log.CanLog`)."""

    def sent(self, frames: list[Frame]) -> None: ...

    def received(self, frame: Frame) -> None: ...


class Link(Protocol):
    """What a master needs of its bus: :class:`CanLink` (the bus itself), or one node's share
    of a bus several masters use (:class:`~drivers.canopen.axes.NodeLink`)."""

    watched_ids: frozenset[int]

    @property
    def name(self) -> str: ...

    def send(self, frames: list[Frame]) -> None: ...

    def recv(self, timeout: float | None) -> Frame | None: ...

    def own_echo(self, frame: Frame) -> bool: ...

    def reconnect(self) -> None: ...

    def shutdown(self) -> None: ...


class CanLink:
    """One bus as the master uses it; ``reopen`` builds the bus again after a lost link."""

    def __init__(self, bus: can.BusABC, *, reopen: Callable[[], can.BusABC] | None = None,
                 trace: FrameTrace | None = None) -> None:
        self.reopen = reopen
        self.trace = trace
        # frames of the watched ids this master sent lately, (monotonic ns, id, data), on a
        # bus that hands a sender its own frames back (``echoes``): they must not pass for
        # another master's
        self.watched_ids: frozenset[int] = frozenset()
        self._own: deque[tuple[int, int, bytes]] = deque(maxlen=OWN_FRAMES_KEPT)
        self._use(bus)

    def _use(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.echoes = type(bus).__module__.startswith(ECHOING_BUS_MODULES)
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
        if self.echoes and self.watched_ids:
            now = time.monotonic_ns()
            self._own.extend((now, can_id, bytes(data)) for can_id, data in frames
                             if can_id in self.watched_ids)
        if self.trace is not None:
            self.trace.sent(frames)

    def own_echo(self, frame: Frame) -> bool:
        """Whether ``frame`` (of a watched id) is one this master sent in the last
        :data:`OWN_ECHO_WINDOW_NS`, handed back by a bus that echoes (each sent frame
        matches once); on other buses, never."""
        if not self.echoes:
            return False
        own, horizon = self._own, time.monotonic_ns() - OWN_ECHO_WINDOW_NS
        while own and own[0][0] < horizon:
            own.popleft()
        can_id, data = frame
        for entry in own:
            if entry[1] == can_id and entry[2] == bytes(data):
                own.remove(entry)
                return True
        return False

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
        return one_line(exc).removeprefix(f"{self.name}: ")

    def reconnect(self) -> None:
        """The bus built again (after a lost link), when the master was given the way."""
        if self.reopen is None:
            return
        with contextlib.suppress(Exception):  # the old connection is gone anyway
            self.bus.shutdown()
        self._use(self.reopen())

    def shutdown(self) -> None:
        self.bus.shutdown()
