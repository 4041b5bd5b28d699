"""An in-process CAN channel for lockstep runs: a frame costs a deque append and a popleft.

python-can's ``virtual`` bus hands frames over through ``queue.Queue`` (a lock, a condition
and a timed wait per frame) and stamps each one with the wall clock. In lockstep the master
and the emulated node run in one thread, one after the other, so none of that is needed:
:class:`DirectChannel` keeps one inbox (a ``deque``) per attached bus, ``send`` appends the
frame to every other inbox, and ``recv`` pops from its own without ever waiting. A frame is
shared by its receivers, not copied; nobody mutates a frame after sending it.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import can


class DirectChannel:
    """The buses attached to one in-process channel."""

    def __init__(self, name: str = "direct") -> None:
        self.name = name
        self.inboxes: list[deque[can.Message]] = []

    def attach(self) -> DirectBus:
        """A new bus on this channel; it receives what every other bus sends from now on."""
        return DirectBus(self)


class DirectBus(can.BusABC):
    """One bus of a :class:`DirectChannel` (a python-can bus; ``recv`` never blocks)."""

    def __init__(self, channel: DirectChannel, **kwargs: Any) -> None:
        self._channel = channel
        self._inbox: deque[can.Message] = deque()
        channel.inboxes.append(self._inbox)
        super().__init__(channel=channel.name, **kwargs)
        self.channel_info = f"direct channel {channel.name}"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        for inbox in self._channel.inboxes:
            if inbox is not self._inbox:
                inbox.append(msg)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        inbox = self._inbox
        return inbox.popleft() if inbox else None

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.recv(), False

    def shutdown(self) -> None:
        if self._inbox in self._channel.inboxes:
            self._channel.inboxes.remove(self._inbox)
        super().shutdown()
