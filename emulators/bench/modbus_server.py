"""A small Modbus server (TCP and RTU) for the emulated bench, with the behaviour of real
devices and the faults of a schedule.

The protocol is small enough to own: an MBAP header (transaction, protocol 0, length, unit)
or an RTU frame (unit, PDU, CRC-16 low byte first) around a PDU; the answers come from
:class:`~hil.emulators.bench.server.BenchDevices` through :func:`answer`. Owning it keeps every
edge a real device has (exception codes, malformed requests, unknown units, a foreign
protocol id, a function the unit lacks) and the faults (:mod:`hil.emulators.faults`: delay, drop,
exception, close, corrupt_crc) independent of any Modbus library's internals.

* TCP: one thread accepts, one thread per connection answers its requests in order. A frame
  with a protocol id other than 0 is discarded whole; the next one is answered.
* RTU: one thread reads the serial line. A request's length follows from its function code
  (FC15/FC16/FC23 carry a byte count, FC43 is read device identification; unknown codes are
  taken as the common 8-byte request);
  a frame with a bad CRC is dropped a byte at a time until the line resynchronises. Only the
  units on the line answer (a request for another unit is silence, as on RS-485).

A :class:`ServedClock` (``clock``) answers its own unit before any fault is played: the
emulator's time, which a lockstep master may hold (:mod:`hil.emulators.bench.timekeeper`), or
which the master in this process holds (``loop_timeout_s``). While a master holds it, time
passes only when the master says, so a wait means nothing: a delay
shorter than the master's request timeout is answered at once, and where the emulator would
leave the master waiting (a dropped answer, a longer delay, an unknown unit, and over RTU a
closed link or a corrupt frame) it answers exception 0x0B at once, as a Modbus gateway whose
device did not answer in time. A silence then only ever means a paused or dead emulator.

Read Device Identification (FC43) is answered before any fault too: a lockstep master asks it
before its session starts the plant and the fault schedule from t = 0, so a fault played on
it would play on the emulator's own clock (a loaded machine slow to start the run: a fault
recorded at a time the run never had, or the run taken for a real bench's and put on the wall
clock).
"""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from hil.emulators.faults import Fault, FaultSchedule

# Modbus exception codes (Modbus Application Protocol V1.1b3, 7)
ILLEGAL_FUNCTION = 0x01
ILLEGAL_ADDRESS = 0x02
ILLEGAL_VALUE = 0x03
GATEWAY_TARGET_FAILED = 0x0B
#: FC43, "encapsulated interface transport" (Read Device Identification, MEI type 0x0E)
IDENTIFICATION = 0x2B

Answer = Callable[[int, bytes], "bytes | None"]  # (unit, request PDU) -> response PDU | None


class UnknownUnitError(LookupError):
    """No device on the line has this unit id."""


class ServedClock(Protocol):
    """The emulator's clock as the server serves it (:mod:`hil.emulators.bench.timekeeper`)."""

    unit: int  # the unit id it answers

    def answer(self, pdu: bytes, peer: object) -> bytes:
        """The response PDU to a request for the clock's unit from ``peer`` (a connection)."""
        ...

    def closed(self, peer: object) -> None:
        """``peer``'s connection ended."""
        ...

    @property
    def master_timeout_s(self) -> float | None:
        """While a lockstep master holds the time: its request timeout; else None."""
        ...


def exception_pdu(function_code: int, code: int) -> bytes:
    return bytes([(function_code | 0x80) & 0xFF, code])


def crc16(frame: bytes) -> bytes:
    """The Modbus RTU CRC-16 of ``frame``, low byte first, as it goes on the line."""
    crc = 0xFFFF
    for byte in frame:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc.to_bytes(2, "little")


def rtu_request_size(head: bytes) -> int | None:
    """The whole RTU request frame's size from its first bytes (None: not enough yet)."""
    if len(head) < 2:
        return None
    code = head[1]
    if code in (15, 16):  # address, count, byte count, values
        return None if len(head) < 7 else 9 + head[6]
    if code == 23:  # read address/count, write address/count, byte count, values
        return None if len(head) < 11 else 13 + head[10]
    if code in (7, 11, 12, 17):  # no data
        return 4
    if code == 43:  # MEI type 14, read device id code, object id
        return 7
    return 8  # the common request: 4 bytes of data


class ModbusServer:
    """Serves ``answer`` over Modbus TCP or RTU in background threads, playing ``faults``.

    ``silent_unknown``: an unknown unit gets no answer (the RTU way) instead of exception 0x0B
    (a TCP gateway whose target did not respond)."""

    def __init__(self, answer: Callable[[int, bytes], bytes], faults: FaultSchedule,
                 silent_unknown: bool) -> None:
        self._answer = answer
        self.faults = faults
        self.silent_unknown = silent_unknown
        self.address: tuple[str, int] | str | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._listener: socket.socket | None = None
        self._connections: set[socket.socket] = set()
        self._lock = threading.Lock()
        self._serial: Any = None
        self.transport = ""  # "tcp" | "rtu", once started
        self.clock: ServedClock | None = None  # answers its own unit, ahead of any fault
        #: lockstep in the master's own process: its request timeout (the plant steps only when
        #: that master says, so, as for a master holding the clock, no request is left waiting)
        self.loop_timeout_s: float | None = None

    # -- starting and stopping --------------------------------------------------------------
    def start_tcp(self, host: str, port: int) -> tuple[str, int]:
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            listener.bind((host, port))
        except OSError:
            listener.close()
            raise
        listener.listen(8)
        self.transport = "tcp"
        listener.settimeout(0.1)
        self._listener = listener
        bound = listener.getsockname()
        self.address = (bound[0], bound[1])
        self._spawn(self._accept, "bench-modbus-tcp")
        return self.address

    def start_serial(self, port: str, baudrate: int, parity: str, stopbits: int,
                     bytesize: int) -> str:
        import serial

        self._serial = serial.Serial(port, baudrate, parity=parity, stopbits=stopbits,
                                     bytesize=bytesize, timeout=0.05)
        self.address = port
        self.transport = "rtu"
        self._spawn(self._serve_rtu, "bench-modbus-rtu")
        return port

    def stop(self) -> None:
        self._stop.set()
        if self._listener is not None:
            self._listener.close()
        with self._lock:
            for connection in self._connections:
                with contextlib.suppress(OSError):
                    connection.shutdown(socket.SHUT_RDWR)
        for thread in self._threads:
            thread.join(timeout=5)
        self._threads.clear()
        if self._serial is not None:
            self._serial.close()
            self._serial = None

    def _spawn(self, target: Callable[..., None], name: str, *args: Any) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        self._threads.append(thread)
        thread.start()

    # -- requests ---------------------------------------------------------------------------
    def respond(self, unit: int, pdu: bytes, peer: object = None
                ) -> tuple[bytes | None, bool, bool]:
        """(the response PDU or None, whether to corrupt its frame, whether to close the
        connection) for one request from ``peer``, after the faults of the schedule."""
        clock = self.clock
        if clock is not None and unit == clock.unit:
            return clock.answer(pdu, peer), False, False
        patience = clock.master_timeout_s if clock is not None else self.loop_timeout_s
        no_answer = exception_pdu(pdu[0], GATEWAY_TARGET_FAILED)
        if pdu[0] == IDENTIFICATION:
            return self._unfaulted(unit, pdu, patience, no_answer), False, False
        for fault in self._active("delay", unit):
            self.faults.hit(fault)
            late_s = fault.params["ms"] / 1000
            if patience is None:
                time.sleep(late_s)
            elif late_s >= patience:
                return no_answer, False, False
        rtu = self.transport == "rtu"
        for fault in self._active("close", unit):
            self.faults.hit(fault)
            if patience is not None and rtu:
                return no_answer, False, False
            return None, False, True
        for fault in self._active("drop", unit):
            if self.faults.hit(fault) % fault.params["every"] == 0:
                return (None if patience is None else no_answer), False, False
        for fault in self._active("exception", unit):
            self.faults.hit(fault)
            return exception_pdu(pdu[0], fault.params["code"]), False, False
        corrupt = False
        for fault in self._active("corrupt_crc", unit):
            self.faults.hit(fault)
            if patience is not None and rtu:
                return no_answer, False, False
            corrupt = True
        return self._unfaulted(unit, pdu, patience, no_answer), corrupt, False

    def _unfaulted(self, unit: int, pdu: bytes, patience: float | None, no_answer: bytes
                   ) -> bytes | None:
        """The device's own answer: for an unknown unit silence (the RTU way, while no
        master holds the time) or ``no_answer``."""
        try:
            return self._answer(unit, pdu)
        except UnknownUnitError:
            return None if self.silent_unknown and patience is None else no_answer

    def _active(self, kind: str, unit: int) -> list[Fault]:
        return [f for f in self.faults.active(kind) if f.params["unit"] in (0, unit)]

    # -- TCP --------------------------------------------------------------------------------
    def _accept(self) -> None:
        assert self._listener is not None
        while not self._stop.is_set():
            try:
                connection, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return  # closed by stop()
            connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._connections.add(connection)
            self._spawn(self._serve_tcp, "bench-modbus-client", connection)

    def _serve_tcp(self, connection: socket.socket) -> None:
        buffer = b""
        try:
            while not self._stop.is_set():
                data = connection.recv(4096)
                if not data:
                    return
                buffer, close = self.answer_tcp(buffer + data, connection, connection.sendall)
                if close:
                    return
        except OSError:
            return
        finally:
            with self._lock:
                self._connections.discard(connection)
            connection.close()
            if self.clock is not None:
                self.clock.closed(connection)

    def answer_tcp(self, buffer: bytes, peer: object, send: Callable[[bytes], object]
                   ) -> tuple[bytes, bool]:
        """Answer the whole Modbus TCP frames at the start of ``buffer`` from ``peer``, each
        answer given to ``send`` as it is made: (what is left of ``buffer``, whether to close
        the connection; the frames after the one that closes it are not answered)."""
        while len(buffer) >= 8:
            tid, protocol, length, unit = struct.unpack_from(">HHHB", buffer)
            if len(buffer) < 6 + length:
                break
            pdu, buffer = buffer[7:6 + length], buffer[6 + length:]
            if protocol != 0 or not pdu:
                continue  # not Modbus: discarded whole
            response, corrupt, close = self.respond(unit, pdu, peer)
            if close:
                return buffer, True
            if response is not None:
                frame = struct.pack(">HHHB", tid, 0, len(response) + 1, unit) + response
                if corrupt:
                    frame = frame[:-1] + bytes([frame[-1] ^ 0xFF])
                send(frame)
        return buffer, False

    def connect_in_process(self) -> Callable[[bytes], tuple[bytes, bool]]:
        """A Modbus TCP connection from a master in this process, answered in its thread
        (:class:`~hil.drivers.bench.lines.InProcessLine`): each call takes request frames and
        gives their answers and whether the server closed the connection."""
        peer = object()
        buffer = b""

        def exchange(frames: bytes) -> tuple[bytes, bool]:
            nonlocal buffer
            answers: list[bytes] = []
            buffer, close = self.answer_tcp(buffer + frames, peer, answers.append)
            if close and self.clock is not None:
                self.clock.closed(peer)
            return b"".join(answers), close

        return exchange

    # -- RTU --------------------------------------------------------------------------------
    def _serve_rtu(self) -> None:
        buffer = b""
        port = self._serial
        while not self._stop.is_set() and port is not None:
            try:
                data = port.read(port.in_waiting or 1)
            except Exception:  # the port went away: nothing more to serve
                return
            if not data:
                buffer = b""  # a silent interval ends any partial frame (RTU's t3.5)
                continue
            buffer += data
            while (size := rtu_request_size(buffer)) is not None and len(buffer) >= size:
                frame = buffer[:size]
                if crc16(frame[:-2]) != frame[-2:]:
                    buffer = buffer[1:]  # not a frame: resynchronise
                    continue
                buffer = buffer[size:]
                unit, pdu = frame[0], frame[1:-2]
                response, corrupt, _ = self.respond(unit, pdu, port)
                if response is not None:
                    reply = bytes([unit]) + response
                    reply += crc16(reply)
                    if corrupt:
                        reply = reply[:-1] + bytes([reply[-1] ^ 0xFF])
                    port.write(reply)
