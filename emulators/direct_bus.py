"""An in-process CAN channel for lockstep runs: a frame costs a deque append and a popleft.

python-can's ``virtual`` bus hands frames over through ``queue.Queue`` (a lock, a condition
and a timed wait per frame) and stamps each one with the wall clock. In lockstep the master
and the emulated node run in one thread, one after the other, so none of that is needed:
:class:`DirectChannel` keeps one inbox (a ``deque``) per attached bus, a send appends the
frame to every other inbox, and a receive pops from its own without ever waiting.

A bus may have an acceptance filter, as a CAN controller has (:meth:`DirectBus.accept`: the
COB-IDs its node serves): then each sender routes a frame by one dict lookup of its COB-ID to
the inboxes that take it, worked out once per COB-ID until a filter changes
(:meth:`DirectChannel.refilter`); several drives on one channel then no longer each receive,
and drop, the others' PDOs.

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

Accepts = Callable[[int], bool]  # an acceptance filter: whether a bus takes a COB-ID


class DirectChannel:
    """The buses attached to one in-process channel."""

    def __init__(self, name: str = "direct") -> None:
        self.name = name
        self.inboxes: list[deque[Frame]] = []
        self.buses: list[DirectBus] = []  # every bus attached, listening or not
        self.filtered = False  # a bus has an acceptance filter: frames go by routes
        #: a frame was sent since the last :meth:`carried_frames`
        self.carried = False

    def attach(self, on_send: Callable[[], None] | None = None, *,
               listen: bool = True) -> DirectBus:
        """A new bus on this channel; it receives what every other bus sends from now on
        (unless not ``listen``: a bus that only sends keeps no inbox, which would only grow).
        ``on_send`` runs after each of its transmissions (a lockstep rig runs the emulated
        node there, so a cycle is function calls)."""
        return DirectBus(self, on_send=on_send, listen=listen)

    def refilter(self) -> None:
        """What a filter accepts changed (or a bus came or went): every route afresh."""
        self.filtered = any(bus.accepts is not None for bus in self.buses)
        for bus in self.buses:
            bus.routes.clear()

    def carried_frames(self) -> bool:
        """Whether a frame was sent since the last call."""
        carried, self.carried = self.carried, False
        return carried


class DirectBus(can.BusABC):
    """One bus of a :class:`DirectChannel` (a python-can bus; receiving never blocks)."""

    def __init__(self, channel: DirectChannel, *, on_send: Callable[[], None] | None = None,
                 listen: bool = True, **kwargs: Any) -> None:
        self._channel = channel
        self._on_send = on_send
        self._inbox: deque[Frame] = deque()
        self.listening = listen
        self.accepts: Accepts | None = None  # the acceptance filter (None: every frame)
        #: the inboxes each COB-ID goes to, when the channel has a filter (worked out once)
        self.routes: dict[int, tuple[deque[Frame], ...]] = {}
        if listen:
            channel.inboxes.append(self._inbox)
        channel.buses.append(self)
        channel.refilter()
        super().__init__(channel=channel.name, **kwargs)
        self.channel_info = f"direct channel {channel.name}"

    def accept(self, accepts: Accepts) -> None:
        """From now on this bus receives only the frames whose COB-ID ``accepts`` takes (it
        must tell :meth:`DirectChannel.refilter` whenever that changes)."""
        self.accepts = accepts
        self._channel.refilter()

    def send_frames(self, frames: list[Frame]) -> None:
        """``frames``, in order, to every other bus of the channel (that accepts them)."""
        channel = self._channel
        if channel.filtered:
            routes = self.routes
            for frame in frames:
                inboxes = routes.get(frame[0])
                if inboxes is None:
                    inboxes = routes[frame[0]] = self._route(frame[0])
                for inbox in inboxes:
                    inbox.append(frame)
        else:
            for inbox in channel.inboxes:
                if inbox is not self._inbox:
                    inbox.extend(frames)
        if frames:
            channel.carried = True
        if self._on_send is not None:
            self._on_send()

    def _route(self, can_id: int) -> tuple[deque[Frame], ...]:
        """The other inboxes that take ``can_id``."""
        return tuple(bus._inbox for bus in self._channel.buses
                     if bus is not self and bus.listening
                     and (bus.accepts is None or bus.accepts(can_id)))

    def recv_frame(self, timeout: float | None = None) -> Frame | None:
        """The oldest frame waiting, or None (never waits: in lockstep nothing else runs)."""
        inbox = self._inbox
        return inbox.popleft() if inbox else None

    @property
    def waiting(self) -> deque[Frame]:
        """The frames waiting, oldest first: the inbox itself (a reader that takes them
        clears it)."""
        return self._inbox

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
        channel = self._channel
        channel.inboxes[:] = [inbox for inbox in channel.inboxes if inbox is not self._inbox]
        channel.buses[:] = [bus for bus in channel.buses if bus is not self]
        channel.refilter()
        super().shutdown()
