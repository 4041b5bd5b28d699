"""Modbus frames into hil's bench emulator: over a real TCP socket, over a real serial line (a
pty pair), and into the clock unit's answers directly.

The rule for the emulator: every answer is a well-formed Modbus answer to a request of the
stream (a normal response or an exception with a code the protocol has), its threads never
die, and its relays change only as an answered write asks.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import time
from collections.abc import Iterator

from hypothesis import strategies as st

from hil.bench.config import load_bench_config
from hil.bench.emulated import make_emulator
from hil.emulators.bench.modbus_server import crc16
from hil.emulators.bench.timekeeper import Timekeeper
from hil.emulators.null_modem import NullModem
from tests.fuzz.harness import LIMITS, Check, HangError, Target, ThreadFailures, bound
from tests.fuzz.strategies import (
    Stream,
    TcpFrame,
    clock_pdus,
    rtu_streams,
    tcp_streams,
)

EXCEPTION_CODES = (1, 2, 3, 4, 6, 0x0B)
WRITES = (5, 15)  # the relay unit's writes: an answered one may change a coil
RTU_SILENCE_S = 0.08  # longer than the emulator's 50 ms read timeout, which ends a partial frame
PROBES, PROBE_WAIT_S = 3, 2.0  # coil reads after the fuzz, each waited for this long at most


def check_answer(pdu: bytes, asked: set[int]) -> None:
    """``pdu`` is a well-formed answer to one of the function codes ``asked``."""
    assert pdu, "an empty answer"
    code = pdu[0] & 0x7F
    assert code in asked, f"answer {pdu.hex()} to function {code}, which nobody asked"
    if pdu[0] & 0x80:
        assert len(pdu) == 2 and pdu[1] in EXCEPTION_CODES, f"bad exception answer {pdu.hex()}"
    elif code in (1, 3, 4):
        assert len(pdu) >= 2 and pdu[1] == len(pdu) - 2, f"bad read answer {pdu.hex()}"
    elif code in (5, 6, 15, 16):
        assert len(pdu) == 5, f"bad write answer {pdu.hex()}"
    elif code == 0x2B:
        assert pdu[1:2] == b"\x0e" and len(pdu) >= 7, f"bad identification {pdu.hex()}"


def split_mbap(data: bytes) -> list[TcpFrame]:
    """The Modbus TCP frames of an answer stream (each must be whole)."""
    frames, pos = [], 0
    while pos < len(data):
        assert len(data) - pos >= 8, f"answer stream ends in a header: {data[pos:].hex()}"
        tid, protocol, length, unit = struct.unpack_from(">HHHB", data, pos)
        assert protocol == 0 and length >= 2, f"bad answer header {data[pos:pos + 7].hex()}"
        assert pos + 6 + length <= len(data), "answer cut short"
        frames.append(TcpFrame(tid, protocol, length, unit, data[pos + 7:pos + 6 + length]))
        pos += 6 + length
    return frames


def requests_in(data: bytes) -> list[TcpFrame]:
    """The Modbus TCP requests a server finds in ``data``: each MBAP header's length says
    where the next one starts (what the stream's frames meant is beside the point)."""
    requests, pos = [], 0
    while len(data) - pos >= 8:
        tid, protocol, length, unit = struct.unpack_from(">HHHB", data, pos)
        if len(data) - pos < 6 + length:
            break
        pdu = data[pos + 7:pos + 6 + length]
        if protocol == 0 and pdu:
            requests.append(TcpFrame(tid, protocol, length, unit, pdu))
        pos += 6 + length
    return requests


def coils_follow(before: list[bool], after: list[bool], answered_writes: int) -> None:
    """The relays moved only through an answered write."""
    if after != before:
        assert answered_writes, \
            f"relays changed {before} -> {after} without an answered write"


@contextlib.contextmanager
def tcp_rig() -> Iterator[Check]:
    """The bench emulator on 127.0.0.1 (a free port), the wall clock not stepping it: each
    case on a new connection, the plant started again before it."""
    bench = make_emulator(load_bench_config())
    bench.serve_tcp()
    with ThreadFailures() as failures:
        def check(stream: Stream) -> None:
            bench.restart()
            before = bench.plant.coils()
            answers = split_mbap(_exchange_tcp(bench.port, stream))
            failures.check()
            requests = iter(requests_in(stream.data))
            for answer in answers:  # in order, each to a request the stream holds
                asked = next((r for r in requests if (r.tid, r.unit) == (answer.tid,
                                                                         answer.unit)), None)
                assert asked is not None, f"answer {answer} to no request, or out of order"
                check_answer(answer.pdu, {asked.pdu[0] & 0x7F})
            writes = sum(1 for a in answers if a.pdu and a.pdu[0] in WRITES)
            coils_follow(before, bench.plant.coils(), writes)

        try:
            yield check
        finally:
            bench.stop()


def _exchange_tcp(port: int, stream: Stream) -> bytes:
    """Send ``stream`` on a new connection, end it, and read every answer until the
    emulator closes (a silence as long as the hang bound is a hang)."""
    with socket.create_connection(("127.0.0.1", port), timeout=LIMITS.hang_s) as sock:
        for chunk in stream.chunks():
            sock.sendall(chunk)
        sock.shutdown(socket.SHUT_WR)
        received = b""
        while True:
            try:
                data = sock.recv(65536)
            except TimeoutError:
                raise HangError("the emulator neither answered nor closed within "
                           f"{LIMITS.hang_s:g} s") from None
            if not data:
                return received
            received += data


@contextlib.contextmanager
def rtu_rig() -> Iterator[Check]:
    """The bench emulator on one end of a pty pair, this side on the other: each case's bytes,
    a silence that ends any partial frame, then a read of the coils that must be answered
    right (the emulator resynchronised)."""
    import serial

    bench = make_emulator(load_bench_config())
    with NullModem() as modem, ThreadFailures() as failures:
        bench.serve_serial(modem.ports[1])
        port = serial.Serial(modem.ports[0], 115200, timeout=RTU_SILENCE_S)
        probe = bytes([1, 1, 0, 0, 0, 8])
        probe += crc16(probe)

        def check(stream: Stream) -> None:
            bench.restart()
            before = bench.plant.coils()
            port.reset_input_buffer()
            for chunk in stream.chunks():
                port.write(chunk)
            answers = _until_silent(port)
            # a loaded machine may keep the emulator from seeing the silence before the probe
            # comes: a probe swallowed so is tried again after another silence
            for _ in range(PROBES):
                after = bench.plant.coils()
                expected = bytes([1, 1, 1, sum(1 << i for i, on in enumerate(after) if on)])
                expected += crc16(expected)
                port.write(probe)
                reply = _read_exactly(port, 6, PROBE_WAIT_S)
                if reply == expected:
                    break
                answers += reply + _until_silent(port)
            failures.check()
            assert reply == expected, \
                f"coil read after the fuzz answered {reply.hex()}: not resynchronised"
            writes = sum(1 for i in range(len(answers) - 7) if answers[i] == 1 and
                         answers[i + 1] in WRITES and crc16(answers[i:i + 6]) ==
                         answers[i + 6:i + 8])
            coils_follow(before, after, writes)

        try:
            yield check
        finally:
            port.close()
            bench.stop()


def _until_silent(port: object) -> bytes:
    """What the line brings until it has been silent for RTU_SILENCE_S (port's timeout)."""
    received, deadline = b"", time.monotonic() + LIMITS.hang_s
    while time.monotonic() < deadline:
        data = port.read(4096)  # type: ignore[attr-defined]
        if not data:
            return received
        received += data
    raise HangError(f"the emulator kept talking for {LIMITS.hang_s:g} s")


def _read_exactly(port: object, size: int, wait_s: float) -> bytes:
    received, deadline = b"", time.monotonic() + wait_s
    while len(received) < size and time.monotonic() < deadline:
        received += port.read(size - len(received))  # type: ignore[attr-defined]
    return received


@contextlib.contextmanager
def clock_rig() -> Iterator[Check]:
    """The clock unit's answers, called as the server calls them (the wire adds only time:
    its framing is the TCP and RTU targets'); a new timekeeper for each case, on the master's
    time (``--clock master``: no wall-clock thread)."""
    bench = make_emulator(load_bench_config())  # not served: its clock's answers are called
    peers = (object(), object())

    def check(requests: list[tuple[int, bytes]]) -> None:
        bench.restart()
        keeper = Timekeeper(bench, "master")
        for who, pdu in requests:
            before_k = bench.plant.k
            with bound(what=f"clock request {pdu.hex()}"):
                answer = keeper.answer(pdu, peers[who])
            check_answer(answer, {pdu[0] & 0x7F})
            if answer[0] & 0x80:
                assert bench.plant.k == before_k, \
                    f"the plant stepped on {pdu.hex()}, refused with {answer.hex()}"

    yield check


def time_request(t_ns: int) -> bytes:
    """The clock unit's ``TIME`` write of ``t_ns``."""
    return struct.pack(">BHHB4H", 16, 0, 4, 8, *[(t_ns >> s) & 0xFFFF for s in (48, 32, 16, 0)])


TARGETS = (
    Target("modbus-tcp-emulator", tcp_streams(), tcp_rig, examples=120),
    Target("modbus-rtu-emulator", rtu_streams(), rtu_rig, examples=12),
    Target("bench-clock-unit", st.lists(st.tuples(st.integers(0, 1), clock_pdus()),
                                        min_size=1, max_size=6), clock_rig, examples=150,
           # found: a TIME of 2^64-1 ns stepped the plant for ever (the answer never came)
           regressions=([(0, time_request(2**64 - 1))],)),
)
