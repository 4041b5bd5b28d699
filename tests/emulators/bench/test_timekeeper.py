"""The bench emulator's identification and clock unit, asked by pymodbus's own client (a master
hil did not write) over Modbus TCP on 127.0.0.1: the registers of
hil/protocols/bench_clock.py, the exceptions, one master at a time."""

from __future__ import annotations

import socket
import time

import pytest
from pymodbus.client import ModbusTcpClient

from hil.bench.config import load_bench_config
from hil.bench.emulated import make_emulator

pytestmark = [pytest.mark.slow]

CLOCK = 248


@pytest.fixture
def emulator():
    bench = make_emulator(load_bench_config())
    bench.serve_tcp()
    bench.follow("auto")
    try:
        yield bench
    finally:
        bench.stop()


def client_of(emulator) -> ModbusTcpClient:
    client = ModbusTcpClient("127.0.0.1", port=emulator.port, timeout=2, retries=0)
    assert client.connect()
    return client


def plant_ns(client: ModbusTcpClient) -> int:
    words = client.read_holding_registers(0, count=4, device_id=CLOCK).registers
    return (words[0] << 48) | (words[1] << 32) | (words[2] << 16) | words[3]


def test_every_device_identifies_itself_as_hils_emulator(emulator):
    client = client_of(emulator)
    try:
        basic = client.read_device_information(read_code=1, device_id=2)
        assert basic.information == {0: b"hil", 1: b"hil-bench-emulator", 2: b"2.0"}
        regular = client.read_device_information(read_code=2, device_id=1)
        assert regular.information[4] == b"hil relay bench emulator"
        assert regular.information[5] == b"relay module"
        one = client.read_device_information(read_code=4, object_id=5, device_id=3)
        assert one.information == {5: b"level sensors"}
        missing = client.read_device_information(read_code=4, object_id=3, device_id=3)
        assert missing.isError() and missing.exception_code == 2
    finally:
        client.close()


def step(client: ModbusTcpClient, number: int, t_ns: int) -> list[int]:
    """A numbered time request (FC23 at register 5): the registers it answers."""
    words = [number, *((t_ns >> s) & 0xFFFF for s in (48, 32, 16, 0))]
    reply = client.readwrite_registers(read_address=5, read_count=5, write_address=5,
                                       values=words, device_id=CLOCK)
    assert not reply.isError(), reply
    return list(reply.registers)


def test_a_master_takes_the_time_steps_the_plant_and_lets_go(emulator):
    client = client_of(emulator)
    try:
        assert client.read_holding_registers(4, count=1, device_id=CLOCK).registers == [0]
        assert not client.write_register(4, 100, device_id=CLOCK).isError()  # takes it
        assert plant_ns(client) == 0 and emulator.plant.k == 0  # started again
        t_ns = 1_230_000_000
        assert step(client, 1, t_ns) == [1, 0, 0, 0x4950, 0x4F80]  # its number, 1.23 s
        assert plant_ns(client) == t_ns and emulator.plant.k == 123
        time.sleep(0.1)  # the wall clock moves nothing meanwhile
        assert emulator.plant.k == 123
        assert client.read_holding_registers(4, count=6, device_id=CLOCK).registers == \
            [1, 1, 0, 0, 0x4950, 0x4F80]  # on a master's time; the last step
        assert not client.write_register(4, 0, device_id=CLOCK).isError()  # lets go
        assert client.read_holding_registers(4, count=1, device_id=CLOCK).registers == [0]
    finally:
        client.close()


def test_a_time_request_asked_again_is_answered_again_and_steps_once(emulator):
    """The same number again (the master asked again: the request or its answer was lost) is
    answered as the first time, with no step, even for another time; a new number steps."""
    client = client_of(emulator)
    try:
        assert not client.write_register(4, 100, device_id=CLOCK).isError()
        first = step(client, 7, 500_000_000)
        assert emulator.plant.k == 50
        assert step(client, 7, 500_000_000) == first and emulator.plant.k == 50
        assert step(client, 7, 900_000_000) == first and emulator.plant.k == 50
        assert step(client, 8, 510_000_000)[0] == 8 and emulator.plant.k == 51
        assert step(client, 9, 200_000_000)[0] == 9 and emulator.plant.k == 51  # never back
        assert not client.write_register(4, 100, device_id=CLOCK).isError()  # a new session
        assert step(client, 9, 10_000_000) == [9, 0, 0, 0x98, 0x9680] \
            and emulator.plant.k == 1  # numbers start afresh with it
    finally:
        client.close()


def test_a_time_too_far_ahead_is_refused_not_stepped_for_ever(emulator):
    # found by the fuzz campaign (tests/fuzz): TIME = 2^64-1 ns stepped the plant for ever
    client = client_of(emulator)
    try:
        assert not client.write_register(4, 100, device_id=CLOCK).isError()
        far = client.readwrite_registers(read_address=5, read_count=5, write_address=5,
                                         values=[1, 0xFFFF, 0xFFFF, 0xFFFF, 0xFFFF],
                                         device_id=CLOCK)
        assert far.isError() and far.exception_code == 3
        assert plant_ns(client) == 0  # not moved
        assert step(client, 2, 1_000_000_000)[0] == 2 and plant_ns(client) == 1_000_000_000
    finally:
        client.close()


def test_one_master_at_a_time_and_the_clocks_registers_only(emulator):
    first, second = client_of(emulator), client_of(emulator)
    try:
        assert not first.write_register(4, 100, device_id=CLOCK).isError()
        busy = second.write_register(4, 100, device_id=CLOCK)
        assert busy.isError() and busy.exception_code == 6
        assert second.write_register(4, 0, device_id=CLOCK).exception_code == 6
        refused = second.readwrite_registers(read_address=5, read_count=5, write_address=5,
                                             values=[1, 0, 0, 0, 0], device_id=CLOCK)
        assert refused.exception_code == 6
        assert first.write_register(3, 1, device_id=CLOCK).exception_code == 2
        assert first.write_registers(0, [0, 0], device_id=CLOCK).exception_code == 1  # FC16
        assert first.readwrite_registers(read_address=0, read_count=5, write_address=5,
                                         values=[1, 0, 0, 0, 0],
                                         device_id=CLOCK).exception_code == 2
        assert first.readwrite_registers(read_address=5, read_count=5, write_address=5,
                                         values=[0, 0, 0, 0, 0],
                                         device_id=CLOCK).exception_code == 3  # number 0
        assert first.read_holding_registers(8, count=3, device_id=CLOCK).exception_code == 2
        assert first.read_coils(0, count=1, device_id=CLOCK).exception_code == 1
        assert second.read_coils(0, count=4, device_id=1).bits[:4] == [False] * 4  # devices
    finally:
        first.close()
        second.close()


def test_a_master_that_closes_its_connection_keeps_the_time_for_a_second(emulator):
    client = client_of(emulator)
    assert not client.write_register(4, 100, device_id=CLOCK).isError()
    client.close()
    again = client_of(emulator)
    try:
        assert again.read_holding_registers(4, count=1, device_id=CLOCK).registers == [1]
        assert emulator.plant.k == 0  # held: no wall-clock step
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and emulator.plant.k == 0:
            time.sleep(0.05)
        assert emulator.plant.k > 0  # gone for longer than the grace: back on the wall clock
        assert again.read_holding_registers(4, count=1, device_id=CLOCK).registers == [0]
    finally:
        again.close()


def test_an_emulator_on_its_wall_clock_refuses_the_time():
    bench = make_emulator(load_bench_config())
    bench.serve_tcp()
    lines: list[str] = []
    bench.follow("wall", lines.append)
    client = client_of(bench)
    try:
        refused = client.write_register(4, 100, device_id=CLOCK)
        assert refused.isError() and refused.exception_code == 1
        assert lines == [f"a lockstep master at 127.0.0.1:{client.socket.getsockname()[1]} "
                         "asked for the plant's time: refused (--clock wall)"]
    finally:
        client.close()
        bench.stop()


def test_a_device_that_gives_no_identity_is_none_and_costs_no_retry():
    """The master's question (drivers/bench/emulator_clock.py): no answer at all (a peer that
    takes the connection and never answers) is None, after one patient try, and the bench's
    retry count is left as it was."""
    from hil.drivers.bench.emulator_clock import identify
    from hil.drivers.bench.modbus import ModbusLink, parse_bus_url

    with socket.create_server(("127.0.0.1", 0)) as silent:  # the kernel takes the connection
        link = ModbusLink(parse_bus_url(f"modbus-tcp://127.0.0.1:{silent.getsockname()[1]}"),
                          0.1, 2)
        try:
            assert identify(link, 1, 0.3) is None
            assert link.retries == 0 and (link.timeout_s, link.attempts) == (0.1, 2)
        finally:
            link.close()


@pytest.mark.parametrize(("spec", "answer"), [
    ("drop@0", "exception 0x0b"), ("delay@0:ms=300", "exception 0x0b"),
    ("exception@0:code=6", "exception 0x06")])
def test_the_identity_is_answered_ahead_of_faults_on_the_emulators_own_clock(spec, answer):
    """A lockstep master asks who the emulator is while the plant still runs on the
    emulator's own clock (``auto``: its wall clock, for however long a loaded machine takes to
    start the run): no fault plays on that question, so none is recorded at a time the run
    never had, and the run is not taken for a real bench's. Its session then plays the fault
    from its own t = 0 (the first poll: a drop or a delay over the request timeout answered
    exception 0x0B at once)."""
    from hil.drivers.bench.emulator_clock import EmulatorClock, identify
    from hil.drivers.bench.modbus import LinkError, ModbusLink, parse_bus_url
    from hil.emulators.bench.server import EmulatedBench
    from hil.emulators.faults import parse_fault

    config = load_bench_config()
    bench = EmulatedBench(config.plant, config.server, [parse_fault(spec)])
    link = ModbusLink(parse_bus_url(bench.serve_tcp()), 0.1, 1)
    bench.follow("auto")
    try:
        assert str(identify(link, 1, 10.0)) == "hil hil-bench-emulator 2.0"
        assert bench.faults.events == []
        EmulatorClock(link).start(0.1)
        with pytest.raises(LinkError, match=answer):
            link.read_coils(1, 0, 4)
        assert [(e["fault"], e["t_s"]) for e in bench.faults.events] == \
            [(str(parse_fault(spec)), 0.0)]
    finally:
        link.close()
        bench.stop()
