"""A socketcand-protocol server (raw mode) on TCP, so CAN emulators are reached over the network.

Protocol (linux-can/socketcand ``doc/protocol.md``): the server greets with ``< hi >``; the client
opens a bus with ``< open can0 >`` (``< ok >``, or ``< error could not open bus >`` and the
connection is closed), switches to raw mode with ``< rawmode >`` (``< ok >``), then sends frames
as ``< send ID LEN B0 B1 ... >`` (hex) and receives every bus frame as
``< frame ID SECS.USECS DATA >`` (DATA = the bytes as one hex string, ID of 3 hex digits for a
standard id, 8 for an extended one). ``< echo >`` is echoed, ``< bcmmode >`` goes back to BCM
mode (where frames are not forwarded); BCM jobs (add, update, subscribe...) are not supported and
answer ``< error unknown command >`` as socketcand answers an unknown command. A malformed
``send`` is ignored (socketcand only logs it).

Bus semantics: a frame sent by one client goes to ``on_data`` (an 11-bit data frame as its id
and data: what an emulated node takes, without a :class:`can.Message` built for it) and
``on_frame`` (every frame, as a message), and to every other client in raw mode; frames from
the node (:meth:`broadcast`) go to every raw-mode client. With ``on_frames`` instead of
``on_data``, the 11-bit data frames of one read (a master's transmission: its RPDOs and the
SYNC, sent together) are handed over together, once the read's commands are done or before
the first that is not a ``send``; the sends of a lone raw-mode client in the form hil's master
writes them (:data:`CANONICAL_SEND`) are taken in one pass, anything else command by command.

One detail differs from socketcand on purpose: right after ``< rawmode >`` / ``< ok >`` the
server holds frames for that client until the client sends its next command, or for
``RAW_HOLD_S`` at most. python-can's client reads the ``< ok >`` with a single ``recv`` and
compares it exactly, so a frame arriving in the same read would break its handshake.

Everything runs in the thread that calls :meth:`serve` (a selector loop), including ``on_frame``
and the periodic ``on_tick``: an emulated node needs no lock of its own. With ``next_frame_ns``
(the node tells when its next cyclic frame, the SYNC, is due) the loop polls the sockets from
``poll_margin_s`` before that time until the frame comes, instead of sleeping in ``select``:
a sleeping process is woken up 50 us to several hundred us after the data arrives (more on a
virtual machine), where a drive answers a SYNC within microseconds.
"""

from __future__ import annotations

import binascii
import contextlib
import logging
import math
import os
import re
import select
import selectors
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import can

from hil.emulators.errors import EmulatorError
from hil.protocols.can_frames import Frame

log = logging.getLogger(__name__)

RAW_HOLD_S = 0.2
POLL_MARGIN_S = 300e-6  # polled from this long before due: a timed wake-up is ~60 us late here
MAX_COMMAND_CHARS = 256
SELECT_FD_LIMIT = 1024  # select() takes descriptors below FD_SETSIZE
#: an 11-bit ``send`` as hil's master writes it (ID of 3 hex digits, LEN, the bytes)
CANONICAL_SEND = re.compile(r"< send ([0-7][0-9A-Fa-f]{2}) ([0-8]) "
                            r"((?:[0-9A-Fa-f]{2}(?: [0-9A-Fa-f]{2})*)?) >")


class StopRequest(Protocol):
    """Anything with ``is_set()``: a threading.Event, or a flag a signal handler sets."""

    def is_set(self) -> bool: ...


MAX_OUTPUT_BYTES = 1 << 20  # a client that stops reading is dropped beyond this backlog


@dataclass
class _Client:
    sock: socket.socket
    peer: str
    mode: str = "nobus"  # nobus -> bcm -> raw
    inbuf: str = ""
    outbuf: bytearray = field(default_factory=bytearray)
    hold_until: float | None = None
    held: list[bytes] = field(default_factory=list)


def format_frame(msg: can.Message) -> bytes:
    """``< frame ID SECS.USECS DATA >`` as socketcand writes it."""
    return frame_text(msg.arbitration_id, bytes(msg.data), msg.timestamp or time.time(),
                      8 if msg.is_extended_id else 3)


def frame_text(can_id: int, data: bytes, stamp: float, id_digits: int = 3) -> bytes:
    """``< frame ID SECS.USECS DATA >`` of a frame received at ``stamp`` (epoch seconds)."""
    return frame_line(can_id, data, stamp_text(stamp), id_digits)


def frame_line(can_id: int, data: bytes, stamp: bytes, id_digits: int = 3) -> bytes:
    """``< frame ID SECS.USECS DATA >`` with its stamp already formatted (:func:`stamp_text`:
    one for every frame sent together)."""
    return b"< frame %0*X %s %s >" % (id_digits, can_id, stamp, binascii.hexlify(data).upper())


def stamp_text(stamp: float) -> bytes:
    """``SECS.USECS`` of ``stamp`` (epoch seconds), as a frame carries it."""
    secs = int(stamp)
    return b"%d.%06d" % (secs, int((stamp - secs) * 1e6))


def parse_send(command: str) -> can.Message | None:
    """A ``< send ID LEN B... >`` command as a message, or None when it is malformed."""
    sent = parse_send_frame(command)
    if sent is None:
        return None
    can_id, data, extended = sent
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=extended,
                       timestamp=time.time())


def parse_send_frame(command: str) -> tuple[int, bytes, bool] | None:
    """A ``< send ID LEN B... >`` command as ``(id, data, extended)``, or None when it is
    malformed (bytes of two hex digits, as hil's master and python-can send them, in one
    call)."""
    parts = command[1:-1].split()
    if len(parts) < 3 or parts[0] != "send":
        return None
    id_text, len_text, byte_texts = parts[1], parts[2], parts[3:]
    try:
        can_id, length = int(id_text, 16), int(len_text, 16)
        data = bytes.fromhex(" ".join(byte_texts)) if all(len(b) == 2 for b in byte_texts) \
            else bytes([int(b, 16) for b in byte_texts])
    except ValueError:
        return None
    extended = len(id_text) == 8
    if length > 8 or length != len(data) or \
            not 0 <= can_id <= (0x1FFFFFFF if extended else 0x7FF):
        return None
    return can_id, data, extended


def _fine_wait_fd(selector: selectors.BaseSelector) -> int | None:
    """The descriptor of an epoll ``selector`` that select() can wait on to the microsecond
    (None: another selector, or a descriptor beyond select()'s range)."""
    epoll = getattr(selectors, "EpollSelector", None)  # Linux only
    if epoll is None or not isinstance(selector, epoll):
        return None
    fd: int = selector.fileno()
    return fd if fd < SELECT_FD_LIMIT else None


class SocketcandServer:
    """Serves one emulated CAN bus named ``channel`` to any number of TCP clients."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 29536,
        *,
        channel: str = "can0",
        on_frame: Callable[[can.Message], None] | None = None,
        on_data: Callable[[int, bytes], None] | None = None,
        on_frames: Callable[[list[Frame]], None] | None = None,
        on_tick: Callable[[], None] | None = None,
        tick_period_s: float = 0.001,
        next_frame_ns: Callable[[int], int | None] | None = None,
        poll_margin_s: float = POLL_MARGIN_S,
    ) -> None:
        self.channel = channel
        self.on_frame = on_frame
        self.on_data = on_data
        self.on_frames = on_frames
        self._read_frames: list[Frame] = []  # this read's frames, for on_frames
        self.on_tick = on_tick
        self.tick_period_s = tick_period_s
        self.next_frame_ns = next_frame_ns
        self.poll_margin_ns = round(poll_margin_s * 1e9)
        #: the time service runs after the frames that come when it is due, its own wake-up
        #: one period later only (a bus gone quiet): a server on a real-time loop's core would
        #: otherwise interrupt that loop once a period
        self.service_follows_frames = False
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._listener.bind((host, port))
        except OSError as exc:
            self._listener.close()
            raise EmulatorError(f"socketcand server cannot listen on {host}:{port}: {exc.strerror}"
                           ) from None
        self._listener.listen(8)
        self._listener.setblocking(False)
        self.address: tuple[str, int] = self._listener.getsockname()[:2]
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ, None)
        self._fine_wait_fd = _fine_wait_fd(self._selector)
        self._clients: dict[socket.socket, _Client] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------------- running
    def serve(self, stop: StopRequest | None = None) -> None:
        """Run the selector loop until ``stop`` (or :meth:`close`) is set."""
        stop = stop or self._stop
        next_tick = time.monotonic()
        while not stop.is_set() and not self._stop.is_set():
            wake = next_tick + (self.tick_period_s if self.service_follows_frames else 0.0)
            timeout = max(0.0, wake - time.monotonic())
            if self.next_frame_ns is not None:
                timeout = min(timeout, self._until_polling())
            events = self._events(timeout)
            if not events and not timeout:
                os.sched_yield()  # polling: a process waiting for this core runs first
            for key, mask in events:
                if key.data is None:
                    self._accept()
                else:
                    client: _Client = key.data
                    if mask & selectors.EVENT_READ:
                        self._read(client)
                    if mask & selectors.EVENT_WRITE and client.sock in self._clients:
                        self._flush(client)
            now = time.monotonic()
            if now >= next_tick:
                self._release_holds(now)
                if self.on_tick is not None:
                    self._call(self.on_tick)
                next_tick = now + self.tick_period_s

    def _events(self, timeout: float) -> list[tuple[selectors.SelectorKey, int]]:
        """The sockets ready within ``timeout`` s, waited for to the microsecond: epoll counts
        whole milliseconds (Python rounds a shorter wait up to one, which would sleep through
        the poll window), so a timed wait is a select() on the epoll descriptor."""
        if self._fine_wait_fd is not None and timeout > 0:
            select.select([self._fine_wait_fd], [], [], timeout)
            timeout = 0.0
        return self._selector.select(timeout)

    def _until_polling(self) -> float:
        """Seconds until the bus is polled for the next expected frame (0: poll now)."""
        assert self.next_frame_ns is not None
        now = time.monotonic_ns()
        due = self.next_frame_ns(now)
        if due is None:
            return math.inf
        return max(0.0, (due - self.poll_margin_ns - now) / 1e9)

    def start(self) -> SocketcandServer:
        """Serve in a background thread (in-process use: tests, demos)."""
        self._thread = threading.Thread(target=self.serve, name="socketcand-server", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        for client in list(self._clients.values()):
            self._drop(client, "server closing")
        with contextlib.suppress(KeyError, ValueError):
            self._selector.unregister(self._listener)
        self._listener.close()
        self._selector.close()

    def __enter__(self) -> SocketcandServer:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    @staticmethod
    def _call(hook: Callable[..., None], *args: object) -> None:
        try:
            hook(*args)
        except Exception:  # the emulator's problem must not stop the bus
            log.exception("socketcand: handler %r failed", hook)

    @property
    def client_count(self) -> int:
        return len(self._clients)

    # --------------------------------------------------------------------- connections
    def _accept(self) -> None:
        try:
            sock, peer = self._listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = _Client(sock, f"{peer[0]}:{peer[1]}")
        self._clients[sock] = client
        self._selector.register(sock, selectors.EVENT_READ, client)
        log.info("socketcand: client %s connected", client.peer)
        self._write(client, b"< hi >")

    def _drop(self, client: _Client, why: str) -> None:
        if self._clients.pop(client.sock, None) is None:
            return
        log.info("socketcand: client %s dropped (%s)", client.peer, why)
        with contextlib.suppress(KeyError, ValueError):
            self._selector.unregister(client.sock)
        client.sock.close()

    def _read(self, client: _Client) -> None:
        try:
            chunk = client.sock.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._drop(client, str(exc))
            return
        if not chunk:
            self._drop(client, "closed by peer")
            return
        client.inbuf += chunk.decode("ascii", errors="replace")
        self._parse(client)

    def _parse(self, client: _Client) -> None:
        buf = client.inbuf
        if self.on_frames is not None and self.on_frame is None and client.mode == "raw" and \
                client.hold_until is None and len(self._clients) == 1:
            buf = buf[self._take_sends(buf):]
        while client.sock in self._clients:
            start = buf.find("<")
            if start < 0:
                buf = ""
                break
            end = buf.find(">", start)
            if end < 0:
                if len(buf) - start > MAX_COMMAND_CHARS:
                    log.warning("socketcand: %s sent an unterminated command", client.peer)
                    buf = ""
                else:
                    buf = buf[start:]
                break
            self._command(client, buf[start:end + 1])
            buf = buf[end + 1:]
        client.inbuf = buf
        self._hand_over()

    def _take_sends(self, buf: str) -> int:
        """The canonical sends at the start of ``buf`` (a lone raw-mode client's, for
        ``on_frames``), taken as :meth:`_command` takes them, in one pass: the position after
        them (the rest, if any, is parsed command by command)."""
        frames, match, pos = self._read_frames, CANONICAL_SEND.match, 0
        while (found := match(buf, pos)) is not None:
            id_text, length, data_text = found.groups()
            data = bytes.fromhex(data_text)
            if len(data) != int(length):
                break  # malformed: logged where it is parsed command by command
            frames.append((int(id_text, 16), data))
            pos = found.end()
        return pos

    def _hand_over(self) -> None:
        """The frames read so far to ``on_frames``, together."""
        if self._read_frames and self.on_frames is not None:
            frames, self._read_frames = self._read_frames, []
            self._call(self.on_frames, frames)

    # ------------------------------------------------------------------------ commands
    def _command(self, client: _Client, command: str) -> None:
        words = command[1:-1].split()
        verb = words[0] if words else ""
        if verb != "send":
            self._hand_over()  # the frames before it are taken before it is answered
        if client.hold_until is not None:
            self._release(client)
        if client.mode == "nobus":
            if verb == "open" and len(words) == 2:
                if words[1] == self.channel:
                    client.mode = "bcm"
                    self._write(client, b"< ok >")
                else:
                    self._write(client, b"< error could not open bus >")
                    self._drop(client, f"asked for unknown bus {words[1]!r}")
            else:
                self._write(client, b"< error unknown command >")
            return
        if verb == "send":
            sent = parse_send_frame(command)
            if sent is None:
                log.warning("socketcand: syntax error in send command from %s: %s",
                            client.peer, command)
                return
            can_id, data, extended = sent
            if len(self._clients) > 1:
                self._forward(can_id, data, extended, exclude=client)
            if not extended:
                if self.on_frames is not None:
                    self._read_frames.append((can_id, data))
                elif self.on_data is not None:
                    self._call(self.on_data, can_id, data)
            if self.on_frame is not None:
                self._call(self.on_frame, can.Message(arbitration_id=can_id, data=data,
                                                      is_extended_id=extended,
                                                      timestamp=time.time()))
        elif verb == "echo" and len(words) == 1:
            self._write(client, b"< echo >")
        elif verb == "rawmode" and len(words) == 1:
            self._write(client, b"< ok >")
            client.mode = "raw"
            client.hold_until = time.monotonic() + RAW_HOLD_S
        elif verb == "bcmmode" and len(words) == 1:
            client.mode = "bcm"
            self._write(client, b"< ok >")
        else:
            self._write(client, b"< error unknown command >")

    # ------------------------------------------------------------------------- output
    def broadcast(self, frames: list[Frame]) -> None:
        """Frames from the emulated node (11-bit, stamped now), to every client in raw mode
        (one write per client: a TPDO pair reaches the master in one TCP segment)."""
        if self._clients and frames:
            stamp = stamp_text(time.time())
            self._forward_text(b"".join([frame_line(can_id, data, stamp)
                                         for can_id, data in frames]), exclude=None)

    def _forward(self, can_id: int, data: bytes, extended: bool, exclude: _Client) -> None:
        """A client's frame to the other raw-mode clients (formatted only if there is one)."""
        if any(c is not exclude and c.mode == "raw" for c in self._clients.values()):
            self._forward_text(frame_text(can_id, data, time.time(), 8 if extended else 3),
                               exclude)

    def _forward_text(self, text: bytes, exclude: _Client | None) -> None:
        for client in list(self._clients.values()):
            if client is exclude or client.mode != "raw":
                continue
            if client.hold_until is not None:
                client.held.append(text)
            else:
                self._write(client, text)

    def _release_holds(self, now: float) -> None:
        for client in list(self._clients.values()):
            if client.hold_until is not None and now >= client.hold_until:
                self._release(client)

    def _release(self, client: _Client) -> None:
        client.hold_until = None
        held, client.held = client.held, []
        if held:
            self._write(client, b"".join(held))

    def _write(self, client: _Client, data: bytes) -> None:
        if client.sock not in self._clients:
            return
        if client.outbuf:
            client.outbuf += data
        else:
            try:
                sent = client.sock.send(data)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError as exc:
                self._drop(client, str(exc))
                return
            if sent < len(data):
                client.outbuf += data[sent:]
                self._selector.modify(client.sock, selectors.EVENT_READ | selectors.EVENT_WRITE,
                                      client)
        if len(client.outbuf) > MAX_OUTPUT_BYTES:
            self._drop(client, "not reading its frames")

    def _flush(self, client: _Client) -> None:
        try:
            sent = client.sock.send(client.outbuf)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._drop(client, str(exc))
            return
        del client.outbuf[:sent]
        if not client.outbuf:
            self._selector.modify(client.sock, selectors.EVENT_READ, client)
