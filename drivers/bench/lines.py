"""A Modbus master's line to the bench: one request out, its answer found in what comes back.

pymodbus frames each request (its PDU classes and framers, its RTU frame sizes and CRC) and
decodes each answer; finding the answer is this module's. pymodbus's own client reads a fresh
buffer for every request: the rest of a frame that came late is left on a TCP connection,
where it garbles the next answers, and over RTU a bad CRC throws away the whole buffer, a good
frame behind it included, while a frame of another function is taken as it comes. Here each
line keeps what it received between requests, and takes for the answer only a frame that is
one:

* Modbus TCP (:class:`MbapLine`; over a socket, :class:`TcpLine`): the frame that carries
  the request's transaction id. A frame of another id is an answer that came late, to a
  request given up on (or posted: a request whose answer nobody waits for): passed over. A
  frame with the id but of another unit or function, or that the caller's check refuses, is a
  confused peer: ``ReplyMismatchError``.
* In this process (:class:`InProcessLine`): Modbus TCP frames handed to a peer that answers
  them in the caller's thread (a lockstep emulator in the loop's process): the same frames, no
  socket and no thread hop; the answer is there when the write returns, or never comes.
* Modbus RTU (:class:`RtuLine`): RTU frames carry no id. A frame whose CRC fails is noise;
  one of another unit or function, or that the caller's check refuses (its length, its echo
  of the address and value), answers someone else or something else (a late answer, another
  master's exchange): passed over. A device answers its requests in order, so the answer to a
  request given up on comes, if it ever does, before the answer to the next one; when the
  next request could take that answer for its own (a read of the same unit, function and
  length, another question), the line first waits it out (:meth:`RtuLine.ask`). An answer to
  the same question asked before may stand for this one's.

Each :meth:`Line.ask` is one try: the request written, the answer waited for up to the
line's ``timeout_s``; the retry rules are the caller's (:class:`~hil.drivers.bench.modbus.
ModbusLink`). ``discarded`` counts the frames passed over.
"""

from __future__ import annotations

import abc
import contextlib
import select
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymodbus.exceptions import ModbusException
from pymodbus.framer import FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU, ModbusPDU

from hil.drivers.errors import DriverError

#: the largest Modbus frame: an RTU ADU is at most 256 bytes, a TCP ADU 260
MAX_FRAME = 260
#: what a frame may raise on its way through pymodbus's decoders (garbage included)
DECODE_ERRORS = (ModbusException, ValueError, IndexError, KeyError, struct.error)

#: RTU: how long (in timeouts) an answer still out is waited for before a request it could
#: pass for (an answer later than that to a read of the same unit, function and length is the
#: one late frame a serial line cannot tell from the next answer)
WAIT_OUT_TIMEOUTS = 5
#: the reads whose answers carry no echo of the request, only a length
READS = (1, 2, 3, 4)

Check = Callable[[ModbusPDU], bool]


class ReplyMismatchError(DriverError):
    """The peer answered the request's transaction with another unit, function or content."""


class Line(abc.ABC):
    """One master's connection to the bench (a TCP socket or a serial port), requests
    answered in turn. ``timeout_s``: how long :meth:`ask` waits for an answer."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self.decoder = DecodePDU(is_server=False)
        self.discarded = 0  # frames passed over: late answers, others' answers, noise
        self._received = bytearray()

    @property
    @abc.abstractmethod
    def connected(self) -> bool:
        """Whether the connection is open."""

    @abc.abstractmethod
    def connect(self) -> bool:
        """Open the connection (True if it is); what was received before is forgotten."""

    @abc.abstractmethod
    def close(self) -> None:
        """Close the connection; idempotent."""

    def _fileno(self) -> int:
        """What :func:`select.select` waits on (for :meth:`_receive`)."""
        raise NotImplementedError

    def _read_available(self) -> bytes:
        """What has arrived (at least one byte: select said so; for :meth:`_receive`);
        raises OSError when the connection is gone."""
        raise NotImplementedError

    @abc.abstractmethod
    def _write(self, frame: bytes) -> None:
        """Send ``frame``; raises OSError when the connection is gone."""

    @abc.abstractmethod
    def _frame(self, request: ModbusPDU) -> bytes:
        """``request`` as it goes on the wire."""

    @abc.abstractmethod
    def _answer(self, request: ModbusPDU, check: Check) -> ModbusPDU | None:
        """The answer to ``request`` among the frames received (consumed up to it; the
        frames before it are passed over), or None while it is not there."""

    def ask(self, request: ModbusPDU, check: Check) -> ModbusPDU | None:
        """``request`` sent, its answer waited for up to ``timeout_s``: the answer (an
        exception response included), or None when none came. ``check`` says whether a
        decoded frame of the request's unit and function answers it. Raises OSError when the
        connection fails, ReplyMismatchError for a confused TCP peer."""
        self._write(self._frame(request))
        deadline = time.monotonic() + self.timeout_s
        while (answer := self._answer(request, check)) is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._receive(remaining):
                return None
        return answer

    def _receive(self, wait_s: float) -> bool:
        """What arrives within ``wait_s``, added to what was received; False when nothing
        did. By default what :func:`select.select` says of :meth:`_fileno`."""
        ready, _, _ = select.select([self._fileno()], [], [], wait_s)
        if not ready:
            return False
        self._received += self._read_available()
        return True

    def _decode(self, pdu_bytes: bytes, unit: int) -> ModbusPDU | None:
        """The answer PDU of ``pdu_bytes`` (function code first), None when pymodbus cannot
        decode it."""
        try:
            pdu = self.decoder.decode(pdu_bytes)
        except DECODE_ERRORS:
            return None
        if pdu is not None:
            pdu.dev_id = unit
        return pdu


def answers(request: ModbusPDU, unit: int, pdu: ModbusPDU, check: Check) -> bool:
    """Whether ``pdu`` from ``unit`` answers ``request``: its unit and function (or that
    function's exception), and ``check`` for a normal answer."""
    if unit != request.dev_id:
        return False
    if pdu.function_code == request.function_code | 0x80:
        return True
    if pdu.function_code != request.function_code:
        return False
    try:
        return bool(check(pdu))
    except (AttributeError, IndexError, TypeError, ValueError):  # a frame too short for it
        return False


def same_shape(first: ModbusPDU, second: ModbusPDU) -> bool:
    """Whether an answer to ``first`` could pass for one to ``second``: reads of the same unit,
    function and length (a write's answer echoes its address and value, a time request's its
    number)."""
    return (first.dev_id, first.function_code) == (second.dev_id, second.function_code) \
        and first.function_code in READS \
        and getattr(first, "count", None) == getattr(second, "count", None)


class MbapLine(Line):
    """Modbus TCP framing (MBAP), whatever carries it: the answer is the frame with the
    request's transaction id."""

    def __init__(self, timeout_s: float) -> None:
        super().__init__(timeout_s)
        self.framer = FramerSocket(self.decoder)
        self._tid = 0
        self._posted: set[int] = set()  # ids of requests whose answers nobody waits for

    def _forget(self) -> None:
        """A new connection: nothing received on the last one is waited for."""
        self._received.clear()
        self._posted.clear()

    def _frame(self, request: ModbusPDU) -> bytes:
        self._tid = self._tid % 0xFFFF + 1  # 1..65535: 0 is no id
        request.transaction_id = self._tid
        frame: bytes = self.framer.buildFrame(request)
        return frame

    def post(self, request: ModbusPDU) -> None:
        """``request`` sent, its answer not waited for: passed over when it comes."""
        self._write(self._frame(request))
        self._posted.add(self._tid)

    def _answer(self, request: ModbusPDU, check: Check) -> ModbusPDU | None:
        received = self._received
        while len(received) >= 8:
            tid, protocol, length, unit = struct.unpack_from(">HHHB", received)
            if protocol != 0 or not 2 <= length <= MAX_FRAME - 6:
                raise ConnectionResetError("the stream is out of step (no Modbus TCP header)")
            if len(received) < 6 + length:
                return None
            pdu_bytes = bytes(received[7:6 + length])
            del received[:6 + length]
            if tid != request.transaction_id:
                if tid in self._posted:
                    self._posted.discard(tid)
                else:
                    self.discarded += 1  # late: its request was given up on
                continue
            pdu = self._decode(pdu_bytes, unit)
            if pdu is None or not answers(request, unit, pdu, check):
                raise ReplyMismatchError("reply does not match the request")
            pdu.transaction_id = tid
            return pdu
        return None


class TcpLine(MbapLine):
    """Modbus TCP to ``host``:``port``."""

    def __init__(self, host: str, port: int, timeout_s: float) -> None:
        super().__init__(timeout_s)
        self.host, self.port = host, port
        self.socket: socket.socket | None = None

    @property
    def connected(self) -> bool:
        return self.socket is not None

    def connect(self) -> bool:
        if self.socket is not None:
            return True
        try:
            self.socket = socket.create_connection((self.host, self.port),
                                                   timeout=self.timeout_s)
        except OSError:
            return False
        # a request posted ahead of the next must not wait for it
        self.socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._forget()
        return True

    def close(self) -> None:
        if self.socket is not None:
            with contextlib.suppress(OSError):
                self.socket.close()
            self.socket = None

    def _fileno(self) -> int:
        assert self.socket is not None
        return self.socket.fileno()

    def _read_available(self) -> bytes:
        assert self.socket is not None
        data = self.socket.recv(4096)
        if not data:
            raise ConnectionResetError("the peer closed the connection")
        return data

    def _write(self, frame: bytes) -> None:
        if self.socket is None:
            raise ConnectionError("not connected")
        self.socket.sendall(frame)


#: one connection to a peer in this process: a request frame in; the frames it answers, and
#: whether the peer then closed the connection
Exchange = Callable[[bytes], tuple[bytes, bool]]


class InProcessLine(MbapLine):
    """Modbus TCP to a peer in this process: ``connect()`` opens a connection (an
    :data:`Exchange`), each request frame is answered by the time it is written. Nothing is
    waited for: an answer the peer did not give is an answer that never comes (a try that
    fails at once), a connection the peer closed is gone, as over a socket."""

    def __init__(self, connect: Callable[[], Exchange], timeout_s: float) -> None:
        super().__init__(timeout_s)
        self._open = connect
        self._exchange: Exchange | None = None
        self._peer_closed = False

    @property
    def connected(self) -> bool:
        return self._exchange is not None

    def connect(self) -> bool:
        if self._exchange is None:
            self._exchange = self._open()
            self._peer_closed = False
            self._forget()
        return True

    def close(self) -> None:
        self._exchange = None

    def _write(self, frame: bytes) -> None:
        if self._exchange is None or self._peer_closed:
            raise ConnectionError("not connected")
        answered, self._peer_closed = self._exchange(frame)
        self._received += answered

    def _receive(self, wait_s: float) -> bool:
        if self._peer_closed:
            raise ConnectionResetError("the peer closed the connection")
        return False  # all it answered came with the write


@dataclass
class Owed:
    """A request given up on whose answers may still come: its frame, unit and function,
    the caller's check, and how many answers (one per try) are still out."""

    frame: bytes
    request: ModbusPDU
    check: Check
    count: int


class RtuLine(Line):
    """Modbus RTU on the serial port ``device`` (``settings``: pyserial's baudrate, parity,
    stopbits, bytesize): the answer is the first whole frame (CRC) of the request's unit and
    function that ``check`` accepts; the frames before it are passed over."""

    def __init__(self, device: str, settings: dict[str, Any], timeout_s: float) -> None:
        super().__init__(timeout_s)
        self.device, self.settings = device, settings
        self.framer = FramerRTU(self.decoder)
        self.port: Any = None  # a pyserial Serial
        self._owed: Owed | None = None
        self._last = b""  # the frame of the request asked last

    @property
    def connected(self) -> bool:
        return self.port is not None

    def connect(self) -> bool:
        if self.port is not None:
            return True
        import serial

        try:  # non-blocking reads: this line waits with select
            self.port = serial.Serial(self.device, **self.settings, timeout=0,
                                      write_timeout=max(self.timeout_s, 1.0), exclusive=True)
        except (OSError, ValueError):
            return False
        self._received.clear()
        self._owed = None
        return True

    def close(self) -> None:
        if self.port is not None:
            with contextlib.suppress(OSError):
                self.port.close()
            self.port = None

    def _fileno(self) -> int:
        return int(self.port.fileno())

    def _read_available(self) -> bytes:
        data: bytes = self.port.read(max(1, self.port.in_waiting))
        return data

    def _write(self, frame: bytes) -> None:
        if self.port is None:
            raise ConnectionError("the serial port is not open")
        self.port.write(frame)

    def _frame(self, request: ModbusPDU) -> bytes:
        frame: bytes = self.framer.buildFrame(request)
        return frame

    def ask(self, request: ModbusPDU, check: Check) -> ModbusPDU | None:
        """As :meth:`Line.ask`; first, what came before the request is passed over, and when
        the answers still out for a request given up on could pass for this one's
        (:func:`same_shape`), they are waited out (:meth:`_wait_out`). A try left unanswered
        leaves its answer out."""
        frame = self._frame(request)
        owed = self._owed
        if owed is not None and owed.frame != frame and same_shape(owed.request, request):
            self._wait_out(owed)
        self._pass_over_what_came()
        self._last = frame
        answer = super().ask(request, check)
        if answer is None:
            owed = self._owed
            if owed is not None and owed.frame == frame:
                owed.count += 1
            else:
                self._owed = Owed(frame, request, check, 1)
        return answer

    def _pass_over_what_came(self) -> None:
        """Before a request: nothing that came before it answers it (a late answer, another
        master's frames, the rest of a garbled frame)."""
        while self._receive(0):
            pass
        self._sift(None)
        self._received.clear()

    def _wait_out(self, owed: Owed) -> None:
        """Until the answers ``owed`` are all in, or the line was silent for
        :data:`WAIT_OUT_TIMEOUTS` timeouts."""
        while self._owed is not None and self._receive(WAIT_OUT_TIMEOUTS * self.timeout_s):
            self._sift(None)
        self._owed = None

    def _answer(self, request: ModbusPDU, check: Check) -> ModbusPDU | None:
        answer = self._sift(lambda unit, pdu: answers(request, unit, pdu, check))
        if answer is not None and self._owed is not None and self._owed.frame != self._last:
            self._owed = None  # answered in order: what it owed came or never will
        return answer

    def _sift(self, wanted: Callable[[int, ModbusPDU], bool] | None) -> ModbusPDU | None:
        """The first frame received that is ``wanted`` (consumed with the frames before it,
        which are passed over; None: every frame is); an answer still out counted in when
        it comes."""
        while (found := self._next_frame()) is not None:
            unit, pdu = found
            if pdu is None:
                self.discarded += 1
                continue
            if wanted is not None and wanted(unit, pdu):
                return pdu
            self.discarded += 1
            owed = self._owed
            if owed is not None and answers(owed.request, unit, pdu, owed.check):
                owed.count -= 1
                if owed.count <= 0:
                    self._owed = None
        return None

    def _next_frame(self) -> tuple[int, ModbusPDU | None] | None:
        """The first whole frame (CRC) received, consumed with the bytes before it: its unit
        and PDU (None: pymodbus cannot decode it); None when there is none yet (what may
        still become one is kept)."""
        received = self._received
        for start in range(len(received) - 3):
            size = self._frame_size(received, start)
            if size is None or start + size > len(received):
                continue
            frame = bytes(received[start:start + size])
            if not FramerRTU.check_CRC(frame[:-2], int.from_bytes(frame[-2:], "big")):
                continue
            del received[:start + size]
            return frame[0], self._decode(frame[1:-2], frame[0])
        if len(received) > MAX_FRAME:
            del received[:-MAX_FRAME]  # noise: no frame starts this far back
        return None

    def _frame_size(self, received: bytearray, start: int) -> int | None:
        """The size of an answer frame starting at ``start`` by its function code (pymodbus's
        RTU sizes), None when no answer starts there."""
        try:
            head = bytes(received[start:start + MAX_FRAME])
            pdu_class = self.decoder.lookupPduClass(head)
            size = pdu_class.calculateRtuFrameSize(head) if pdu_class is not None else 0
        except DECODE_ERRORS:
            return None
        return size if 4 <= size <= MAX_FRAME else None
