"""The bench emulator over real Modbus: loopback TCP and RTU on a real pty pair.

Lockstep throughout (the test steps the plant), so every value read can be compared with the
plant's own snapshot of that step.
"""

from __future__ import annotations

import socket
import struct
import time

import numpy as np
import pytest
import serial
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.framer.rtu import FramerRTU

from hil.bench.config import load_bench_config
from hil.bench.emulated import make_emulator
from hil.emulators.null_modem import NullModem
from tests.pymodbus_bench import ANSWER_S

pytestmark = [pytest.mark.timeout(60), pytest.mark.slow]

CONFIG = load_bench_config()
METER = CONFIG.data["meter"]["registers"]
RESERVED = (0x002C, 0x0032, 0x0036, 0x003A, 0x0040, 0x0044)  # SDM630 words with no quantity


class Bus:
    """An emulator plus a pymodbus client and a raw-frame channel on one transport."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.emulator = make_emulator(CONFIG)
        self.modem = None
        if kind == "tcp":
            self.emulator.serve_tcp()
            self.client = ModbusTcpClient("127.0.0.1", port=self.emulator.port, timeout=ANSWER_S,
                                          retries=0)
            self.raw_socket = socket.create_connection(("127.0.0.1", self.emulator.port), 2)
        else:
            self.modem = NullModem()
            self.emulator.serve_serial(self.modem.ports[1])
            self.client = ModbusSerialClient(self.modem.ports[0], baudrate=115200, timeout=ANSWER_S,
                                             retries=0)
        assert self.client.connect()
        self._tid = 100

    def raw(self, unit: int, pdu: bytes, wait_s: float = ANSWER_S) -> bytes | None:
        """Send one request PDU as-is; return the reply PDU (function code on), None if none
        within ``wait_s``."""
        if self.kind == "tcp":
            self._tid += 1
            self.raw_socket.sendall(struct.pack(">HHHB", self._tid, 0, len(pdu) + 1, unit) + pdu)
            self.raw_socket.settimeout(wait_s)
            try:
                header = self.raw_socket.recv(7)
            except TimeoutError:
                return None
            tid, _, length, reply_unit = struct.unpack(">HHHB", header)
            assert (tid, reply_unit) == (self._tid, unit)
            return self.raw_socket.recv(length - 1)
        port = self.client.socket
        frame = bytes([unit]) + pdu
        port.reset_input_buffer()
        port.write(frame + FramerRTU.compute_CRC(frame).to_bytes(2, "big"))
        deadline, reply, patience = time.monotonic() + wait_s, b"", port.timeout
        port.timeout = 0.05  # short reads, the deadline checked between them
        try:
            while time.monotonic() < deadline:
                reply += port.read(port.in_waiting or 1)
                if len(reply) >= 5 and FramerRTU.check_CRC(reply[:-2],
                                                           int.from_bytes(reply[-2:], "big")):
                    assert reply[0] == unit
                    return reply[1:-2]
            return None
        finally:
            port.timeout = patience

    def close(self) -> None:
        self.client.close()
        if self.kind == "tcp":
            self.raw_socket.close()
        self.emulator.stop()
        if self.modem is not None:
            self.modem.close()


@pytest.fixture(params=["tcp", "rtu"])
def bus(request):
    b = Bus(request.param)
    yield b
    b.close()


def floats(registers: list[int]) -> list[float]:
    return list(struct.unpack(f">{len(registers) // 2}f", struct.pack(f">{len(registers)}H",
                                                                      *registers)))


def test_coils_switch_the_plant(bus):
    plant = bus.emulator.plant
    assert not bus.client.write_coil(2, True, device_id=1).isError()
    assert bus.client.read_coils(0, count=8, device_id=1).bits[:8] == [
        False, False, True, False, False, False, False, False]
    assert not bus.client.write_coils(4, [True, False, True, True], device_id=1).isError()
    assert plant.coils() == [False, False, True, False, True, False, True, True]
    plant.step()
    assert (0, 2, True) in plant.coil_log                  # the plant acted from the next step
    assert plant.load_va()["P1"] > 200                     # and P1 draws its inrush
    assert not bus.client.write_coil(2, False, device_id=1).isError()
    assert bus.client.read_coils(2, count=1, device_id=1).bits[0] is False


def test_all_meter_registers_match_the_plant_snapshot(bus):
    plant = bus.emulator.plant
    for coil in (0, 1, 2):                                 # M1, M2, P1
        bus.client.write_coil(coil, True, device_id=1)
    for _ in range(2):
        for _ in range(150):
            plant.step()
        reply = bus.client.read_input_registers(0, count=76, device_id=2)
        values = floats(reply.registers)
        meter = plant.snapshot.meter
        for name, address in METER.items():
            assert values[address // 2] == np.float32(meter[name]), name
        for address in RESERVED:
            assert values[address // 2] == 0.0
        by_name = {name: values[address // 2] for name, address in METER.items()}
        assert by_name["total_va"] == pytest.approx(
            by_name["va_l1"] + by_name["va_l2"] + by_name["va_l3"], rel=1e-6)
        assert by_name["total_w"] == pytest.approx(
            by_name["power_w_l1"] + by_name["power_w_l2"] + by_name["power_w_l3"], rel=1e-6)
        loads = plant.load_va()
        assert by_name["va_l2"] == pytest.approx(
            loads["base"] + loads["M1"] + loads["M2"] + loads["P1"], abs=7.5)  # 5 sigma
        assert by_name["va_l1"] == 0.0 and by_name["va_l3"] == 0.0
        assert by_name["current_l2"] == pytest.approx(by_name["va_l2"] / by_name["voltage_l2"],
                                                      rel=1e-6)
        assert by_name["frequency_hz"] == 50.0 and by_name["import_kwh"] > 0


def test_level_registers_match_the_plant(bus):
    plant = bus.emulator.plant
    bus.client.write_coil(3, True, device_id=1)           # P2 refills q2
    for _ in range(100):
        plant.step()
    q1, q2 = floats(bus.client.read_input_registers(0, count=4, device_id=3).registers)
    assert q1 == 55.0 and q2 == pytest.approx(72.0, abs=1e-5)
    assert (q1, q2) == (np.float32(plant.snapshot.levels["q1"]),
                        np.float32(plant.snapshot.levels["q2"]))


EXCEPTIONS = [
    # (unit, request PDU, expected exception code, why)
    (1, struct.pack(">BHH", 5, 2, 0x1234), 3, "FC05 value other than FF00/0000"),
    (1, struct.pack(">BHH", 5, 8, 0xFF00), 2, "FC05 coil beyond the module"),
    (1, struct.pack(">BHH", 1, 0, 9), 2, "FC01 past the last coil"),
    (1, struct.pack(">BHH", 1, 0, 0), 3, "FC01 quantity 0"),
    (1, struct.pack(">BHHBBB", 15, 0, 8, 2, 0xFF, 0), 3, "FC15 byte count != quantity"),
    (2, struct.pack(">BHH", 4, 0, 82), 3, "FC04 over the meter's 80 registers"),
    (2, struct.pack(">BHH", 4, 0, 200), 3, "FC04 over the spec's 125 registers"),
    (2, struct.pack(">BHH", 4, 0x50, 2), 2, "FC04 outside the meter map"),
    (2, struct.pack(">BHH", 4, 0x1000, 2), 2, "FC04 far outside the meter map"),
    (2, struct.pack(">BHH", 4, 1, 2), 2, "FC04 splitting a float"),
    (3, struct.pack(">BHH", 4, 4, 2), 2, "FC04 past the last level"),
    (2, struct.pack(">BHH", 3, 0, 2), 1, "FC03: the meter has input registers only"),
    (1, struct.pack(">BHH", 4, 0, 2), 1, "FC04 to the relay module"),
    (2, struct.pack(">BHH", 1, 0, 1), 1, "FC01 to the meter"),
    (3, struct.pack(">BHH", 5, 0, 0x1234), 1, "FC05 to the level sensors: function first"),
]


def test_exception_codes(bus):
    for unit, pdu, code, why in EXCEPTIONS:
        reply = bus.raw(unit, pdu)
        assert reply == bytes([pdu[0] | 0x80, code]), why
    assert bus.emulator.plant.coils() == [False] * 8       # no refused write got through
    assert bus.raw(1, struct.pack(">BHH", 5, 2, 0xFF00)) == struct.pack(">BHH", 5, 2, 0xFF00)
    assert bus.raw(2, struct.pack(">BHH", 4, 0, 80))[:2] == bytes([4, 160])  # 80 is allowed


def test_unknown_unit(bus):
    reply = bus.raw(9, struct.pack(">BHH", 4, 0, 2), wait_s=0.3)  # RTU: none comes
    if bus.kind == "tcp":
        assert reply == bytes([0x84, 0x0B])                # gateway: target did not respond
    else:
        assert reply is None                               # RS-485: nobody has that address
    assert bus.raw(2, struct.pack(">BHH", 4, 0, 2))[0] == 4  # the bus still works


def test_rtu_emulator_answers_only_its_units_on_a_shared_line():
    with NullModem() as modem, make_emulator(CONFIG) as emulator:
        emulator.serve_serial(modem.ports[1])
        with serial.Serial(modem.ports[0], 115200, timeout=ANSWER_S) as port:
            frame = bytes([3, 4, 0, 0, 0, 4])
            port.write(frame + FramerRTU.compute_CRC(frame).to_bytes(2, "big"))
            reply = port.read(5 + 8)
        assert reply[:3] == bytes([3, 4, 8]) and FramerRTU.check_CRC(
            reply[:-2], int.from_bytes(reply[-2:], "big"))
        assert floats(list(struct.unpack(">4H", reply[3:11]))) == [55.0, 65.0]
