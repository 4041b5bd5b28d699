"""An in-process CAN channel for lockstep runs: a frame costs a deque append and a popleft.

python-can's ``virtual`` bus hands frames over through ``queue.Queue`` (a lock, a condition
and a timed wait per frame) and stamps each one with the wall clock. In lockstep the master
and the emulated node run in one thread, one after the other, so none of that is needed:
:class:`DirectChannel` keeps one inbox (a ``deque``) per attached bus, a send appends the
frame to every other inbox, and a receive pops from its own without ever waiting.

Frames travel as :data:`~hil.protocols.can_frames.Frame` tuples ``(id, data)``: the master and the
node exchange them through ``send_frames`` / ``recv_frame`` without building a
:class:`can.Message`. A :class:`DirectBus` is also a python-can bus (``send`` / ``recv``), for
observers and other masters on the channel.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

import can

from hil.protocols.can_frames import Frame, from_message, to_message


class DirectChannel:
    """The buses attached to one in-process channel."""

    def __init__(self, name: str = "direct") -> None:
        self.name = name
        self.inboxes: list[deque[Frame]] = []

    def attach(self, on_send: Callable[[], None] | None = None, *,
               listen: bool = True) -> DirectBus:
        """A new bus on this channel; it receives what every other bus sends from now on
        (unless not ``listen``: a bus that only sends keeps no inbox, which would only grow).
        ``on_send`` runs after each of its transmissions (a lockstep rig runs the emulated
        node there, so a cycle is function calls)."""
        return DirectBus(self, on_send=on_send, listen=listen)


class DirectBus(can.BusABC):
    """One bus of a :class:`DirectChannel` (a python-can bus; receiving never blocks)."""

    def __init__(self, channel: DirectChannel, *, on_send: Callable[[], None] | None = None,
                 listen: bool = True, **kwargs: Any) -> None:
        self._channel = channel
        self._on_send = on_send
        self._inbox: deque[Frame] = deque()
        if listen:
            channel.inboxes.append(self._inbox)
        super().__init__(channel=channel.name, **kwargs)
        self.channel_info = f"direct channel {channel.name}"

    def send_frames(self, frames: list[Frame]) -> None:
        """``frames``, in order, to every other bus of the channel."""
        for inbox in self._channel.inboxes:
            if inbox is not self._inbox:
                inbox.extend(frames)
        if self._on_send is not None:
            self._on_send()

    def recv_frame(self, timeout: float | None = None) -> Frame | None:
        """The oldest frame waiting, or None (never waits: in lockstep nothing else runs)."""
        inbox = self._inbox
        return inbox.popleft() if inbox else None

    def take_frames(self) -> list[Frame]:
        """Every frame waiting, oldest first (none left waiting)."""
        inbox = self._inbox
        frames = list(inbox)
        inbox.clear()
        return frames

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        frame = from_message(msg)
        if frame is not None:
            self.send_frames([frame])

    def recv(self, timeout: float | None = None) -> can.Message | None:
        frame = self.recv_frame()
        return None if frame is None else to_message(frame)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.recv(), False

    def shutdown(self) -> None:
        # by identity: deques compare by their frames, and another bus's may equal this one's
        self._channel.inboxes[:] = [inbox for inbox in self._channel.inboxes
                                    if inbox is not self._inbox]
        super().shutdown()
