"""The bench emulator's Modbus edges, walked with raw frames over a real TCP socket: every
function code 1..127 against every unit, malformed requests, unknown units, protocol ids."""

from __future__ import annotations

import socket
import struct

import pytest

from hil.bench.config import load_bench_config
from hil.bench.emulated import make_emulator
from tests.pymodbus_bench import ANSWER_S

REAL_FUNCTIONS = {1: (1, 5, 15), 2: (4,), 3: (4,)}  # relays, meter, levels (bench.toml [units])


class RawTcp:
    """One Modbus TCP connection sending hand-built frames."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=2)
        self.tid = 0

    def ask(self, unit: int, pdu: bytes, protocol: int = 0, wait_s: float = ANSWER_S
            ) -> bytes | None:
        self.tid += 1
        self.sock.sendall(struct.pack(">HHHB", self.tid, protocol, len(pdu) + 1, unit) + pdu)
        return self.reply(wait_s)

    def reply(self, wait_s: float) -> bytes | None:
        self.sock.settimeout(wait_s)
        try:
            header = self._exactly(7)
        except TimeoutError:
            return None
        tid, protocol, length, _unit = struct.unpack(">HHHB", header)
        assert protocol == 0
        assert tid == self.tid, "a reply to another request"
        return self._exactly(length - 1)

    def _exactly(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            if not chunk:
                raise ConnectionError("closed by the emulator")
            data += chunk
        return data


@pytest.fixture(scope="module")
def bench():
    emulator = make_emulator(load_bench_config(None).emulating(None, None))
    emulator.serve_tcp()
    yield emulator
    emulator.stop()


@pytest.fixture
def raw(bench):
    channel = RawTcp(bench.port)
    yield channel
    channel.sock.close()


def test_every_function_code_against_every_unit(raw):
    """A function the real device lacks: exception 1 with function byte FC|0x80."""
    for unit, served in REAL_FUNCTIONS.items():
        for code in range(1, 128):
            body = {5: struct.pack(">HH", 4, 0),  # spare coil 4 off
                    15: struct.pack(">HHBB", 4, 1, 1, 0)}.get(code, struct.pack(">HH", 0, 2))
            reply = raw.ask(unit, bytes([code]) + body)
            assert reply is not None, f"unit {unit} FC{code}: no answer"
            if code in served:
                assert reply[0] == code, f"unit {unit} FC{code}: {reply.hex()}"
            else:
                assert reply == bytes([code | 0x80, 1]), f"unit {unit} FC{code}: {reply.hex()}"


@pytest.mark.parametrize(("unit", "pdu", "code"), [
    (1, struct.pack(">BHH", 1, 0, 0), 3),          # zero coils
    (1, struct.pack(">BHH", 1, 0, 2001), 3),       # more than the specification allows
    (1, struct.pack(">BHH", 1, 6, 3), 2),          # past coil 7
    (1, struct.pack(">BHH", 5, 8, 0xFF00), 2),     # no coil 8
    (1, struct.pack(">BHH", 5, 0, 0x1234), 3),     # neither FF00 nor 0000
    (1, struct.pack(">BHHB", 15, 0, 9, 1) + b"\xff", 3),  # byte count disagrees
    (1, bytes([1, 0]), 3),                         # too short for FC01
    (2, struct.pack(">BHH", 4, 0, 82), 3),         # the SDM630 reads at most 80 registers
    (2, struct.pack(">BHH", 4, 0x50, 2), 2),       # outside the meter's map
    (2, struct.pack(">BHH", 4, 1, 2), 2),          # splits a float
    (2, bytes([4, 0]), 3),                         # too short for FC04
    (3, struct.pack(">BHH", 4, 0, 6), 2),          # past the last level
    (2, bytes([16, 0]), 1),                        # a function it lacks, however short
])
def test_out_of_range_and_malformed(raw, unit, pdu, code):
    assert raw.ask(unit, pdu) == bytes([pdu[0] | 0x80, code])


def test_unknown_unit_is_a_gateway_exception_over_tcp(raw):
    assert raw.ask(9, struct.pack(">BHH", 4, 0, 2)) == bytes([0x84, 0x0B])
    assert raw.ask(9, bytes([43, 14, 1, 0])) == bytes([43 | 0x80, 0x0B])


def test_a_frame_with_a_protocol_id_is_discarded_and_the_next_answered(raw):
    assert raw.ask(2, struct.pack(">BHH", 4, 0, 2), protocol=1, wait_s=0.3) is None
    reply = raw.ask(2, struct.pack(">BHH", 4, 0, 2))
    assert reply is not None and reply[:2] == bytes([4, 4])
    # and when both arrive in one segment
    raw.tid += 1
    bad = struct.pack(">HHHB", raw.tid, 7, 6, 2) + struct.pack(">BHH", 4, 0, 2)
    raw.tid += 1
    good = struct.pack(">HHHB", raw.tid, 0, 6, 1) + struct.pack(">BHH", 1, 0, 8)
    raw.sock.sendall(bad + good)
    reply = raw.reply(ANSWER_S)
    assert reply is not None and reply[:2] == bytes([1, 1])


@pytest.mark.parametrize("code", [3, 8, 100])
def test_a_missing_function_over_rtu_is_exception_1_with_a_good_crc(code):
    import serial
    from pymodbus.framer.rtu import FramerRTU

    from hil.emulators.null_modem import NullModem

    with NullModem() as modem, make_emulator(
            load_bench_config(None).emulating(None, None)) as emulator:
        emulator.serve_serial(modem.ports[1])
        with serial.Serial(modem.ports[0], 115200, timeout=ANSWER_S) as port:
            frame = bytes([2, code, 0, 0, 0, 2])
            port.write(frame + FramerRTU.compute_CRC(frame).to_bytes(2, "big"))
            reply = port.read(5)
    assert reply[:3] == bytes([2, code | 0x80, 1])
    assert FramerRTU.check_CRC(reply[:3], int.from_bytes(reply[3:5], "big"))
