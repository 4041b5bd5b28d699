"""CAN data frames as the drive master and the emulated node pass them: ``(id, data)``.

CiA 301 traffic is 11-bit data frames only, so a frame needs no more than its identifier and
its bytes. A tuple costs a fraction of a :class:`can.Message` to build and to read. Buses that
carry such frames natively (:class:`~hil.drivers.socketcand_bus.SocketcandBus`, the in-process
:class:`~hil.emulators.direct_bus.DirectBus`) have ``send_frames`` / ``recv_frame``; any other
python-can bus gets them through :class:`MessageFrames`, which converts at the edge and drops
error, remote, 29-bit and FD frames: no CiA 301 object travels in them.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import can

#: an 11-bit data frame: (identifier, data of 0..8 bytes)
Frame = tuple[int, bytes]


@runtime_checkable
class FrameBus(Protocol):
    """A bus that sends and receives :data:`Frame` tuples."""

    def send_frames(self, frames: list[Frame]) -> None:
        """``frames`` in this order (in one transmission where the transport allows)."""

    def recv_frame(self, timeout: float | None = None) -> Frame | None:
        """The next frame within ``timeout`` seconds (None: wait for one), or None."""


def to_message(frame: Frame) -> can.Message:
    """The python-can message of ``frame`` (11-bit data frame)."""
    return can.Message(arbitration_id=frame[0], data=frame[1], is_extended_id=False)


def from_message(msg: can.Message) -> Frame | None:
    """The frame ``msg`` carries, or None for an error, remote, 29-bit or FD frame."""
    if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id or msg.is_fd:
        return None
    return msg.arbitration_id, bytes(msg.data[: msg.dlc])


class MessageFrames:
    """:class:`FrameBus` over any python-can bus: a :class:`can.Message` per frame."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus

    def send_frames(self, frames: list[Frame]) -> None:
        for frame in frames:
            self.bus.send(to_message(frame))

    def recv_frame(self, timeout: float | None = None) -> Frame | None:
        """The next frame; a frame :func:`from_message` drops is skipped (and the wait for
        the next one starts over)."""
        while (msg := self.bus.recv(timeout)) is not None:
            frame = from_message(msg)
            if frame is not None:
                return frame
        return None


def frames_of(bus: can.BusABC) -> FrameBus:
    """``bus`` itself when it carries :data:`Frame` tuples natively, else an adapter."""
    return bus if isinstance(bus, FrameBus) else MessageFrames(bus)
