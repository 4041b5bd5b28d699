"""The master's side of the bus: CAN frames as ``(id, data)`` tuples, sent in one call per
cycle, received with a deadline, every one also handed to a trace (``--can-log``) if any.

Bus errors become :class:`~hil.drivers.canopen.errors.DriveLinkLostError` naming the bus.
"""

from __future__ import annotations

import contextlib
from collections import deque
from collections.abc import Callable, Sized
from typing import Protocol

import can

from hil.drivers.canopen.errors import DriveLinkLostError, one_line
from hil.protocols.can_frames import Frame, frames_of
from hil.protocols.cia301 import SYNC_COB_ID

OWN_FRAMES_KEPT = 256
#: python-can buses that hand a sender its own frames back (multicast loopback)
ECHOING_BUS_MODULES = ("can.interfaces.udp_multicast",)


class FrameTrace(Protocol):
    """Where a copy of every frame goes (:class:`hil.drivers.canopen.can_log.CanLog`)."""

    def sent(self, frames: list[Frame]) -> None: ...

    def received(self, frame: Frame) -> None: ...


class Link(Protocol):
    """What a master needs of its bus: :class:`CanLink` (the bus itself), or one node's share
    of a bus several masters use (:class:`~hil.drivers.canopen.axes.NodeLink`)."""

    watched_ids: frozenset[int]

    @property
    def name(self) -> str: ...

    @property
    def syncs_sent(self) -> int: ...

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
        # frames of the watched ids this master sent whose echo has not come back yet, (id,
        # data), on a bus that hands a sender its own frames back (``echoes``): they must not
        # pass for another master's
        self.watched_ids: frozenset[int] = frozenset()
        self._own: deque[tuple[int, bytes]] = deque(maxlen=OWN_FRAMES_KEPT)
        self.syncs_sent = 0  # SYNCs this link put on the bus: a lockstep master's time
        self._use(bus)

    def _use(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.echoes = type(bus).__module__.startswith(ECHOING_BUS_MODULES)
        frames = frames_of(bus)
        self._send_frames, self._recv_frame = frames.send_frames, frames.recv_frame
        # the bus hands every frame waiting in one call (the in-process one): :meth:`take_frames`
        self.takes_frames = callable(getattr(bus, "take_frames", None))
        #: the frames waiting, where such a bus keeps them in a queue of its own: empty, a
        #: look finds nothing (None: only a look tells)
        self.waiting: Sized | None = getattr(bus, "waiting", None) if self.takes_frames \
            else None

    @property
    def name(self) -> str:
        return str(self.bus.channel_info)

    def send(self, frames: list[Frame]) -> None:
        """``frames`` in this order, in one transmission where the transport allows."""
        try:
            self._send_frames(frames)
        except (can.CanError, OSError) as exc:
            raise DriveLinkLostError(f"cannot send on {self.name}: {self._detail(exc)}") from None
        for can_id, _ in frames:
            if can_id == SYNC_COB_ID:
                self.syncs_sent += 1
        if self.echoes and self.watched_ids:
            self._own.extend((can_id, bytes(data)) for can_id, data in frames
                             if can_id in self.watched_ids)
        if self.trace is not None:
            self.trace.sent(frames)

    def own_echo(self, frame: Frame) -> bool:
        """Whether ``frame`` (of a watched id) is one this master sent, handed back by a bus
        that echoes: each frame sent matches one echo, however late the master reads it (a
        busy machine), and a frame beyond them is another master's; on other buses, never."""
        if not self.echoes:
            return False
        entry = (frame[0], bytes(frame[1]))
        if entry in self._own:
            self._own.remove(entry)
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

    def take_frames(self) -> list[Frame]:
        """Every frame already here, oldest first, in one call (what :meth:`recv` ``(0)``
        gives one call after the other until None): on a bus that :attr:`takes_frames`."""
        try:
            frames: list[Frame] = self.bus.take_frames()  # type: ignore[attr-defined]
        except (can.CanError, OSError) as exc:
            raise DriveLinkLostError(f"cannot read {self.name}: {self._detail(exc)}") from None
        if frames and self.trace is not None:
            for frame in frames:
                self.trace.received(frame)
        return frames

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
