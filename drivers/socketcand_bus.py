"""A python-can bus for a socketcand gateway (raw mode), built for a cyclic exchange at 2 kHz.

python-can ships a socketcand interface; this one speaks the same protocol
(linux-can/socketcand ``doc/protocol.md``) with the cost of a cycle in mind:

* :meth:`SocketcandBus.send_frames` puts several frames (RPDO, SYNC, heartbeat) in one TCP
  write: one system call, one wake-up of the gateway, where python-can's client makes a
  ``sendall`` and a ``setsockopt`` per frame;
* a read is one non-blocking ``recv`` of everything waiting; ``select`` runs only when
  nothing is buffered and the caller is willing to wait;
* :meth:`SocketcandBus.recv_frame` parses a reply straight into a
  :data:`~hil.protocols.can_frames.Frame` tuple, without a :class:`can.Message`;
* frames the gateway sends in the same read as the handshake's ``< ok >`` (the real daemon
  does) are kept, not taken for a broken handshake.

It is a :class:`can.BusABC` too, so anything written for python-can buses works with it.
"""

from __future__ import annotations

import select
import socket
import time
from collections import deque
from typing import Any

import can

from hil.protocols.can_frames import Frame

HANDSHAKE_TIMEOUT_S = 2.0
MAX_COMMAND_BYTES = 256  # no socketcand command is longer; a longer one is garbage
MAX_SKIPPED_REPLIES = 2000  # replies in a row that are not frames: the gateway is broken
MAX_JUNK_BYTES = 1 << 16    # bytes in a row that hold no reply at all: the same


def format_send(msg: can.Message) -> bytes:
    """``< send ID LEN B0 B1 ... >`` for one frame (ID: 3 hex digits, 8 when extended)."""
    if msg.is_extended_id:
        return send_text(msg.arbitration_id & 0x1FFFFFFF, bytes(msg.data[: msg.dlc]), 8)
    return send_text(msg.arbitration_id & 0x7FF, bytes(msg.data[: msg.dlc]))


def send_text(can_id: int, data: bytes, id_digits: int = 3) -> bytes:
    """``< send ID LEN B0 B1 ... >`` for an identifier and its data."""
    return b"< send %0*X %X %s >" % (id_digits, can_id, len(data), data.hex(" ").upper().encode())


def shown(command: bytes) -> str:
    """A gateway's reply as an error quotes it: on one line (control characters escaped)."""
    return command.decode("ascii", "replace").encode("unicode_escape").decode("ascii")


def parse_frame(command: bytes) -> Frame | None:
    """An 11-bit ``< frame ID SECS.USECS DATA >`` as a frame; None for any other reply."""
    words = command[1:-1].split()
    if len(words) < 3 or words[0] != b"frame" or len(words[1]) == 8:
        return None
    try:
        can_id = int(words[1], 16)
        data = bytes.fromhex(b"".join(words[3:]).decode("ascii"))
    except ValueError:
        return None
    return (can_id, data) if 0 <= can_id <= 0x7FF and len(data) <= 8 else None


def parse_reply(command: bytes, channel: str) -> can.Message | None:
    """A ``< frame ID SECS.USECS DATA >`` or ``< error ... >`` as a message; None for any
    other reply (``< ok >``, ``< echo >``) and for a frame that does not parse (an identifier
    beyond its 11 or 29 bits among them)."""
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
    extended = len(words[1]) == 8
    if len(data) > 8 or not 0 <= can_id <= (0x1FFFFFFF if extended else 0x7FF):
        return None
    return can.Message(timestamp=stamp, arbitration_id=can_id, data=data,
                       is_extended_id=extended, is_rx=True, channel=channel)


class SocketcandBus(can.BusABC):
    """One CAN bus (``channel``) of the socketcand gateway at ``host:port``, in raw mode.

    Connection and handshake problems raise :class:`can.CanInitializationError`; a connection
    lost later raises :class:`can.CanOperationError` from :meth:`send` or :meth:`recv`."""

    def __init__(self, channel: str = "can0", host: str = "127.0.0.1", port: int = 29536,
                 *, timeout_s: float = HANDSHAKE_TIMEOUT_S, **kwargs: Any) -> None:
        self.channel = channel
        self.channel_info = f"socketcand {channel}@{host}:{port}"
        self._inbuf = bytearray()
        self._replies: deque[bytes] = deque()  # complete commands, parsed when read
        self._skipped = 0   # replies in a row that were not frames
        self._junk = 0      # bytes read in a row without a complete reply
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
        self._split_replies()  # what came in the same read as the last ``< ok >``
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
                        f"{shown(command)}")
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

    def send_frames(self, frames: list[Frame]) -> None:
        """Several 11-bit frames in one TCP write (they reach the bus in this order)."""
        self._write(b"".join(send_text(can_id, data) for can_id, data in frames))

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
        command = self._next_reply(timeout)
        return (None if command is None else parse_reply(command, self.channel)), False

    def recv_frame(self, timeout: float | None = None) -> Frame | None:
        """The next 11-bit data frame within ``timeout`` s (None: wait for one), or None;
        other replies (error and 29-bit frames) are skipped. The deadline is absolute:
        replies that are not frames do not extend it, and :data:`MAX_SKIPPED_REPLIES` of them
        in a row (a gateway flooding errors or junk) raise :class:`can.CanOperationError`."""
        deadline = None if timeout is None else time.monotonic() + timeout
        remaining = timeout
        while (command := self._next_reply(remaining)) is not None:
            frame = parse_frame(command)
            if frame is not None:
                self._skipped = 0
                return frame
            self._skip(command)
            if deadline is not None:
                remaining = max(0.0, deadline - time.monotonic())
        return None

    def _skip(self, command: bytes) -> None:
        self._skipped += 1
        if self._skipped >= MAX_SKIPPED_REPLIES:
            self._skipped = 0
            raise can.CanOperationError(
                f"{self.channel_info}: the gateway sent {MAX_SKIPPED_REPLIES} replies in a row "
                f"that are not frames (last: {shown(command[:60])})")

    def _next_reply(self, timeout: float | None) -> bytes | None:
        """The next complete reply, waiting up to ``timeout`` s when none is buffered."""
        replies = self._replies
        if not replies and not self._read_available() and (timeout is None or timeout > 0):
            # nothing was waiting: sleep until something comes or the time is up
            try:
                ready, _, _ = select.select([self._sock], [], [], timeout)
            except (OSError, ValueError) as exc:
                raise can.CanOperationError(f"{self.channel_info}: receive failed: {exc}"
                                            ) from None
            if ready:
                self._read_available()
        return replies.popleft() if replies else None

    def _read_available(self) -> bool:
        """Read whatever the socket holds and split off the complete replies; True if it read."""
        try:
            chunk = self._sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return False
        except OSError as exc:
            raise can.CanOperationError(f"{self.channel_info}: receive failed: {exc}") from None
        if not chunk:
            raise can.CanOperationError(f"{self.channel_info}: the gateway closed the connection")
        self._inbuf += chunk
        before = len(self._replies)
        self._split_replies()
        self._junk = 0 if len(self._replies) > before else self._junk + len(chunk)
        if self._junk > MAX_JUNK_BYTES:
            self._junk = 0
            raise can.CanOperationError(
                f"{self.channel_info}: the gateway sent {MAX_JUNK_BYTES} bytes in a row that "
                "hold no socketcand reply")
        return True

    def _split_replies(self) -> None:
        while (command := self._next_command()) is not None:
            self._replies.append(command)

    def shutdown(self) -> None:
        super().shutdown()
        self._sock.close()
