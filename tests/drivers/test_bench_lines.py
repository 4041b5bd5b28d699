"""Answers matched to their request (drivers/bench/lines.py), against scripted peers over the
real wire: a raw TCP server on 127.0.0.1 and a raw serial peer at the far end of a pty pair,
both writing frames by hand (CRC by pymodbus), so every late, foreign, garbled and split frame
is one the test chose. Over TCP a late answer is passed over by its transaction id, on the
same connection; over RTU a frame of another unit, function or length, or with a bad CRC, is
passed over and the answer taken in the same try; an answer still out that could pass for the
next request's is waited out first."""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Callable

import pytest
import serial
from pymodbus.framer.rtu import FramerRTU

from hil.drivers.bench.modbus import LinkError, ModbusLink, parse_bus_url
from hil.emulators.null_modem import NullModem
from tests.pymodbus_bench import ANSWER_S

pytestmark = [pytest.mark.timeout(60)]

#: what a peer sends for one request: (seconds to wait first, bytes), in turn
Reply = list[tuple[float, bytes]]


def registers_pdu(*words: int) -> bytes:
    """An FC04 answer PDU of ``words``."""
    return struct.pack(f">BB{len(words)}H", 4, 2 * len(words), *words)


def rtu(unit: int, pdu: bytes) -> bytes:
    frame = bytes([unit]) + pdu
    return frame + FramerRTU.compute_CRC(frame).to_bytes(2, "big")


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


class TcpPeer:
    """A Modbus TCP server of one connection at a time; ``script(tid, unit, pdu)`` says what
    each request gets (nothing: silence)."""

    def __init__(self, script: Callable[[int, int, bytes], Reply]) -> None:
        self.script = script
        self.requests: list[tuple[int, bytes]] = []  # (tid, pdu)
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"modbus-tcp://127.0.0.1:{self.listener.getsockname()[1]}"
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                connection, _ = self.listener.accept()
            except OSError:
                return
            buffer = b""
            with connection:
                while data := connection.recv(4096):
                    buffer += data
                    while len(buffer) >= 7 and len(buffer) >= 6 + buffer[5]:
                        tid, _, length, unit = struct.unpack_from(">HHHB", buffer)
                        pdu, buffer = buffer[7:6 + length], buffer[6 + length:]
                        self.requests.append((tid, pdu))
                        for wait_s, chunk in self.script(tid, unit, pdu):
                            time.sleep(wait_s)
                            connection.sendall(chunk)

    def close(self) -> None:
        self.listener.close()


class SerialPeer:
    """A serial peer at ``modem.ports[1]``: each 8-byte request frame (FC01-FC06) gets
    ``script(n, frame)`` (n counts the requests from 0), in turn."""

    def __init__(self, modem: NullModem, script: Callable[[int, bytes], Reply]) -> None:
        self.script = script
        self.requests: list[bytes] = []
        self.port = serial.Serial(modem.ports[1], 115200, timeout=0.05)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            buffer += self.port.read(64)
            while len(buffer) >= 8:
                frame, buffer = buffer[:8], buffer[8:]
                self.requests.append(frame)
                for wait_s, chunk in self.script(len(self.requests) - 1, frame):
                    time.sleep(wait_s)
                    self.port.write(chunk)

    def close(self) -> None:
        self._stop.set()
        self.thread.join(5)
        self.port.close()


#: a try's timeout where the answer a test waits for comes at once: a second for a loaded
#: machine to deliver it (the peer is a thread of the test's process)
ONE_TRY_S = 1.0


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_a_late_answer_is_passed_over_by_its_transaction_id_on_the_same_connection():
    """The first try of a request gets no answer in time; its answer comes just before the
    second try's, in one segment: the second try takes its own, by id."""
    def script(tid: int, unit: int, pdu: bytes) -> Reply:
        if tid == 1:
            return []  # answered with the next one
        return [(0.0, mbap(1, unit, registers_pdu(0x1111, 0x1111))
                 + mbap(tid, unit, registers_pdu(0x2222, 0x2222)))]

    peer = TcpPeer(script)
    link = ModbusLink(parse_bus_url(peer.url), timeout_s=ONE_TRY_S, attempts=2)
    try:
        assert link.read_floats(2, 0, 2) == list(struct.unpack(">f", b"\x22\x22\x22\x22"))
        assert (link.retries, link.discarded, link.connections) == (1, 1, 1)
        assert [tid for tid, _ in peer.requests] == [1, 2]
    finally:
        link.close()
        peer.close()


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_a_late_answer_split_across_the_timeout_keeps_the_connection_in_step():
    """Half of the first try's late frame before that try gives up, the rest during the next
    try: the frame is completed and passed over, the next try's answer found (what was
    received is kept from one try to the next)."""
    late = mbap(1, 2, registers_pdu(0x1111, 0x1111))

    def script(tid: int, unit: int, pdu: bytes) -> Reply:
        if tid == 1:
            return [(0.0, late[:5])]
        return [(0.0, late[5:] + mbap(tid, unit, registers_pdu(0x4000, 0)))]

    peer = TcpPeer(script)
    link = ModbusLink(parse_bus_url(peer.url), timeout_s=ONE_TRY_S, attempts=2)
    try:
        assert link.read_floats(2, 0, 2) == [2.0]
        assert (link.retries, link.discarded, link.connections) == (1, 1, 1)
    finally:
        link.close()
        peer.close()


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_a_request_given_up_on_closes_its_connection():
    """No backlog of requests given up on builds on the peer's side: the next request goes on
    a new connection."""
    def script(tid: int, unit: int, pdu: bytes) -> Reply:
        return [] if tid == 1 else [(0.0, mbap(tid, unit, registers_pdu(0x4000, 0)))]

    peer = TcpPeer(script)
    link = ModbusLink(parse_bus_url(peer.url), timeout_s=ONE_TRY_S, attempts=1)
    try:
        with pytest.raises(LinkError, match=r"no answer within 1 s"):
            link.read_floats(2, 0, 2)
        assert link.read_floats(2, 0, 2) == [2.0]
        assert link.connections == 2
    finally:
        link.close()
        peer.close()


def test_an_answer_of_the_right_id_but_another_function_is_a_confused_peer():
    """Refused, the connection dropped, the request asked again on a new one."""
    def script(tid: int, unit: int, pdu: bytes) -> Reply:
        body = b"\x01\x01\x00" if tid == 1 else registers_pdu(0x4000, 0)  # FC01 for FC04
        return [(0.0, mbap(tid, unit, body))]

    peer = TcpPeer(script)
    link = ModbusLink(parse_bus_url(peer.url), timeout_s=ANSWER_S, attempts=2)
    try:
        assert link.read_floats(2, 0, 2) == [2.0]
        assert (link.retries, link.connections) == (1, 2)
    finally:
        link.close()
        peer.close()


def rtu_link(modem: NullModem, timeout_s: float, attempts: int = 1) -> ModbusLink:
    return ModbusLink(parse_bus_url(f"modbus-rtu://{modem.ports[0]}"), timeout_s, attempts)


def test_foreign_and_garbled_frames_are_passed_over_in_the_same_try():
    """Before the answer: another unit's answer, an answer of another function, one of another
    length, noise and a frame whose CRC is wrong; the answer is taken in the first try."""
    answer = rtu(2, registers_pdu(0x4000, 0))
    broken = bytearray(rtu(2, registers_pdu(0x3F80, 0)))
    broken[4] ^= 0x10

    def script(_n: int, _frame: bytes) -> Reply:
        return [(0.0, rtu(3, registers_pdu(0x3F80, 0)) + rtu(2, b"\x01\x01\x00")
                 + rtu(2, registers_pdu(1, 2, 3, 4)) + b"\x00\xff\x17" + bytes(broken)
                 + answer[:6]), (0.01, answer[6:])]

    with NullModem() as modem:
        peer = SerialPeer(modem, script)
        link = rtu_link(modem, timeout_s=ANSWER_S)
        try:
            assert link.read_floats(2, 0, 2) == [2.0]
            assert link.retries == 0
            assert link.discarded >= 3  # the unit 3, FC01 and 4-register frames
        finally:
            link.close()
            peer.close()


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_a_garbled_answer_is_a_lost_one_asked_again():
    def script(n: int, _frame: bytes) -> Reply:
        answer = bytearray(rtu(2, registers_pdu(0x4000, n)))
        if n == 0:
            answer[3] ^= 0x01  # one bit flipped on the line
        return [(0.0, bytes(answer))]

    with NullModem() as modem:
        peer = SerialPeer(modem, script)
        link = rtu_link(modem, timeout_s=ONE_TRY_S, attempts=2)
        try:
            assert link.read_floats(2, 0, 2) == list(struct.unpack(">f", b"\x40\x00\x00\x01"))
            assert (link.retries, len(peer.requests)) == (1, 2)
        finally:
            link.close()
            peer.close()


@pytest.mark.slow
def test_an_answer_still_out_is_waited_out_before_a_request_it_could_pass_for():
    """Request A (2 registers at 0) gives up after 0.15 s; its answer comes 0.4 s late. The
    next request B (2 registers at 0x10: the same unit, function and length) is sent only
    after it: B gets its own answer, not A's. (The line waits 5 timeouts, 0.75 s, for A's
    answer: half a second to spare for a loaded machine, either side.)"""
    def script(n: int, frame: bytes) -> Reply:
        address = struct.unpack_from(">H", frame, 2)[0]
        value = 0x4000 if address == 0 else 0x4040  # 2.0 for A, 3.0 for B
        return [(0.4 if n == 0 else 0.0, rtu(2, registers_pdu(value, 0)))]

    with NullModem() as modem:
        peer = SerialPeer(modem, script)
        link = rtu_link(modem, timeout_s=0.15)
        try:
            with pytest.raises(LinkError):
                link.read_floats(2, 0, 2)
            with link.patient(ANSWER_S):
                assert link.read_floats(2, 0x10, 2) == [3.0]
            assert link.discarded == 1  # A's answer
        finally:
            link.close()
            peer.close()


def test_a_serial_request_patient_for_long_is_asked_again_every_timeout():
    """Patient (lockstep over the wire, identification): a lost request is asked again every
    timeout_s within the wait, not waited for the whole of it."""
    def script(n: int, _frame: bytes) -> Reply:
        return [] if n < 2 else [(0.0, rtu(2, registers_pdu(0x4000, 0)))]  # 2 lost

    with NullModem() as modem:
        peer = SerialPeer(modem, script)
        # the third request's answer comes at once: a loaded machine (make test's niced
        # workers) may still hand it over 100 ms late, which would be one more retry
        link = rtu_link(modem, timeout_s=0.5)
        try:
            began = time.monotonic()
            with link.patient(ANSWER_S):
                assert link.read_floats(2, 0, 2) == [2.0]
            assert time.monotonic() - began < ANSWER_S / 2
            assert (link.retries, len(peer.requests)) == (2, 3)
        finally:
            link.close()
            peer.close()


@pytest.mark.slow
def test_an_answer_that_came_before_the_request_does_not_answer_it():
    """The same question asked again after a given-up try: the old answer, which came in
    between, is passed over and the new one taken."""
    def script(n: int, _frame: bytes) -> Reply:
        return [(0.3 if n == 0 else 0.0, rtu(2, registers_pdu(0x4000 + 0x40 * n, 0)))]

    with NullModem() as modem:
        peer = SerialPeer(modem, script)
        link = rtu_link(modem, timeout_s=0.1)
        try:
            with pytest.raises(LinkError):
                link.read_floats(2, 0, 2)
            deadline = time.monotonic() + ANSWER_S  # the old answer has come
            while link.line.port.in_waiting == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            with link.patient(ANSWER_S):
                assert link.read_floats(2, 0, 2) == [3.0]
            assert link.discarded == 1
        finally:
            link.close()
            peer.close()
