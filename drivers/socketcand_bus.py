"""A python-can bus for a socketcand gateway (raw mode), built for a cyclic exchange at 2 kHz.

python-can ships a socketcand interface; this one speaks the same protocol
(linux-can/socketcand ``doc/protocol.md``) with the cost of a cycle in mind:

* :meth:`SocketcandBus.send_many` puts several frames (RPDO, SYNC, heartbeat) in one TCP write:
  one system call, one wake-up of the gateway, where python-can's client makes a ``sendall``
  and a ``setsockopt`` per frame;
* a read is one non-blocking ``recv`` of everything waiting, parsed as bytes; ``select`` runs
  only when nothing is buffered and the caller is willing to wait;
* frames the gateway sends in the same read as the handshake's ``< ok >`` (the real daemon
  does) are kept, not taken for a broken handshake.

It is a :class:`can.BusABC`, so anything written for python-can buses works with it.
"""

from __future__ import annotations

import select
import socket
import time
from collections import deque
from typing import Any

import can

HANDSHAKE_TIMEOUT_S = 2.0
MAX_COMMAND_BYTES = 256  # no socketcand command is longer; a longer one is garbage


def format_send(msg: can.Message) -> bytes:
    """``< send ID LEN B0 B1 ... >`` for one frame (ID: 3 hex digits, 8 when extended)."""
    can_id = (f"{msg.arbitration_id & 0x1FFFFFFF:08X}" if msg.is_extended_id
              else f"{msg.arbitration_id & 0x7FF:03X}")
    data = bytes(msg.data[: msg.dlc])
    body = " ".join(f"{b:02X}" for b in data)
    return f"< send {can_id} {len(data):X} {body} >".encode("ascii")


def parse_reply(command: bytes, channel: str) -> can.Message | None:
    """A ``< frame ID SECS.USECS DATA >`` or ``< error ... >`` as a message; None for any
    other reply (``< ok >``, ``< echo >``) and for a frame that does not parse."""
    words = command[1:-1].split()
    if len(words) < 3 or words[0] not in (b"frame", b"error"):
        return None
    try:
        can_id = int(words[1], 16)
        stamp = float(words[2])
        data = bytes.fromhex(b"".join(words[3:]).decode("ascii"))
    except ValueError:
        return None
    if words[0] == b"error":  # socketcand sends no detail: one zero byte, as python-can does
        return can.Message(timestamp=stamp, arbitration_id=can_id & 0x1FFFFFFF, data=b"\0",
                           is_error_frame=True, is_extended_id=True, is_rx=True,
                           channel=channel)
    if len(data) > 8:
        return None
    return can.Message(timestamp=stamp, arbitration_id=can_id, data=data,
                       is_extended_id=len(words[1]) == 8, is_rx=True, channel=channel)


class SocketcandBus(can.BusABC):
    """One CAN bus (``channel``) of the socketcand gateway at ``host:port``, in raw mode.

    Connection and handshake problems raise :class:`can.CanInitializationError`; a connection
    lost later raises :class:`can.CanOperationError` from :meth:`send` or :meth:`recv`."""

    def __init__(self, channel: str = "can0", host: str = "127.0.0.1", port: int = 29536,
                 *, timeout_s: float = HANDSHAKE_TIMEOUT_S, **kwargs: Any) -> None:
        self.channel = channel
        self.channel_info = f"socketcand {channel}@{host}:{port}"
        self._inbuf = bytearray()
        self._frames: deque[can.Message] = deque()
        try:
            self._sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise can.CanInitializationError(
                f"cannot connect to socketcand at {host}:{port}: "
                f"{exc.strerror or type(exc).__name__}") from None
        try:
            self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._handshake(channel, timeout_s)
        except BaseException:
            self._sock.close()
            raise
        self._sock.setblocking(False)
        super().__init__(channel=channel, **kwargs)

    # ----------------------------------------------------------------------- handshake
    def _handshake(self, channel: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        self._expect(b"< hi >", deadline, "greeting")
        self._sock.sendall(f"< open {channel} >".encode("ascii"))
        self._expect(b"< ok >", deadline, f"opening bus {channel!r}")
        self._sock.sendall(b"< rawmode >")
        self._expect(b"< ok >", deadline, "raw mode")

    def _expect(self, wanted: bytes, deadline: float, what: str) -> None:
        while True:
            command = self._next_command()
            if command is not None:
                if command != wanted:
                    raise can.CanInitializationError(
                        f"{self.channel_info}, {what}: expected {wanted.decode()}, got "
                        f"{command.decode('ascii', 'replace')}")
                return
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise can.CanInitializationError(f"{self.channel_info}, {what}: no answer")
            self._sock.settimeout(remaining)
            try:
                chunk = self._sock.recv(4096)
            except OSError as exc:
                raise can.CanInitializationError(
                    f"{self.channel_info}, {what}: {exc.strerror or type(exc).__name__}"
                ) from None
            if not chunk:
                raise can.CanInitializationError(f"{self.channel_info}, {what}: connection "
                                                 "closed")
            self._inbuf += chunk

    def _next_command(self) -> bytes | None:
        """The next complete ``< ... >`` from the input buffer (garbage before it dropped)."""
        buf = self._inbuf
        start = buf.find(b"<")
        if start < 0:
            buf.clear()
            return None
        end = buf.find(b">", start)
        if end < 0:
            if len(buf) - start > MAX_COMMAND_BYTES:
                buf.clear()
            elif start:
                del buf[:start]
            return None
        command = bytes(buf[start:end + 1])
        del buf[:end + 1]
        return command

    # ---------------------------------------------------------------------------- I/O
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._write(format_send(msg))

    def send_many(self, messages: list[can.Message]) -> None:
        """Several frames in one TCP write (they reach the bus in this order)."""
        self._write(b"".join(format_send(msg) for msg in messages))

    def _write(self, data: bytes) -> None:
        try:
            self._sock.sendall(data)
        except BlockingIOError:  # the kernel buffer is full: wait for room (rare)
            self._sock.setblocking(True)
            try:
                self._sock.sendall(data)
            except OSError as exc:
                raise can.CanOperationError(f"{self.channel_info}: send failed: {exc}") from None
            finally:
                self._sock.setblocking(False)
        except OSError as exc:
            raise can.CanOperationError(f"{self.channel_info}: send failed: {exc}") from None

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        frames = self._frames
        if not frames and not self._read_available() and (timeout is None or timeout > 0):
            # nothing was waiting: sleep until something comes or the time is up
            try:
                ready, _, _ = select.select([self._sock], [], [], timeout)
            except (OSError, ValueError) as exc:
                raise can.CanOperationError(f"{self.channel_info}: receive failed: {exc}"
                                            ) from None
            if ready:
                self._read_available()
        return (frames.popleft() if frames else None), False

    def _read_available(self) -> bool:
        """Read whatever the socket holds and parse the complete frames; True if it read."""
        try:
            chunk = self._sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return False
        except OSError as exc:
            raise can.CanOperationError(f"{self.channel_info}: receive failed: {exc}") from None
        if not chunk:
            raise can.CanOperationError(f"{self.channel_info}: the gateway closed the connection")
        self._inbuf += chunk
        channel = self.channel
        while (command := self._next_command()) is not None:
            msg = parse_reply(command, channel)
            if msg is not None:
                self._frames.append(msg)
        return True

    def shutdown(self) -> None:
        super().shutdown()
        self._sock.close()
