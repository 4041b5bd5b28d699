"""The lockstep emulated bench's line (drivers/bench/lines.py ``InProcessLine``): the loop's
Modbus driver hands its TCP frames to the emulator's server in its own thread. What it gets
is what the same driver gets over the server's socket on 127.0.0.1, answers and faults alike:
an exception answered, a connection the server closes (lost, then opened again). And the
frames it hands over are those a Modbus server hil did not write takes: pymodbus's own
(tests/pymodbus_bench.py), each relayed to it on a socket of its own."""

from __future__ import annotations

import functools
import socket
import struct
from collections.abc import Callable, Iterator

import pytest

from hil.bench.config import load_bench_config
from hil.drivers.bench.lines import Exchange, InProcessLine
from hil.drivers.bench.modbus import (
    DeviceError,
    LinkError,
    ModbusBenchDriver,
    ModbusLink,
    parse_bus_url,
)
from hil.emulators.bench.server import EmulatedBench
from hil.emulators.faults import parse_fault
from tests.pymodbus_bench import ANSWER_S, PymodbusBench

CONFIG = load_bench_config()
TIMEOUT_S = 0.5


@pytest.fixture
def emulator() -> Iterator[EmulatedBench]:
    """The emulated bench, lockstep in this process: closes the connection on every request
    in plant time [1, 1.02) s and answers exception 6 (busy) to the meter's in [2, 2.01)."""
    faults = [parse_fault(s) for s in ("close@1-1.02", "exception@2-2.01:code=4,unit=2")]
    with EmulatedBench(CONFIG.plant, CONFIG.server, faults) as bench:
        bench.serve_tcp()
        bench.hold_in_process(TIMEOUT_S)
        yield bench


def drivers(emulator: EmulatedBench) -> tuple[ModbusBenchDriver, ModbusBenchDriver]:
    """The same driver over the socket and in this process."""
    spec = parse_bus_url(emulator.url)
    over_socket = ModbusLink(spec, TIMEOUT_S, 2)
    in_process = ModbusLink(spec, TIMEOUT_S, 2,
                            InProcessLine(emulator.connect_in_process, TIMEOUT_S))
    return (ModbusBenchDriver(over_socket, CONFIG.map),
            ModbusBenchDriver(in_process, CONFIG.map))


def outcome(read) -> object:
    try:
        return read()
    except (LinkError, DeviceError) as exc:
        return f"{type(exc).__name__}: {exc}"


def test_the_in_process_line_gets_what_the_socket_gets_faults_included(emulator):
    socket_driver, line_driver = drivers(emulator)
    relay = next(iter(CONFIG.map.relays))
    seen = []
    for t_s in (0.0, 1.0, 1.5, 2.0, 3.0):
        emulator.step(round((t_s - emulator.plant.t_s) / emulator.plant.dt))
        for driver in (socket_driver, line_driver):
            switch = functools.partial(driver.write_relay, relay, True)
            seen.append((t_s, driver is line_driver, outcome(driver.read_power),
                         outcome(driver.read_levels), outcome(switch)))
    by_line = {t_s: [] for t_s, *_ in seen}
    for t_s, _, *results in seen:
        by_line[t_s].append(results)
    for t_s, (over_socket, in_process) in by_line.items():
        assert in_process == over_socket, t_s
    assert "LinkError" in str(by_line[1.0][0])         # closed on every try: given up
    assert "exception 0x04" in str(by_line[2.0][0])    # the meter's exception, at once
    assert isinstance(by_line[3.0][0][0], dict)        # and answering again
    links = [d.link for d in (socket_driver, line_driver)]
    assert [(k.connections, k.retries, k.requests) for k in links] == \
        [(links[0].connections, links[0].retries, links[0].requests)] * 2
    assert links[1].connections > 1 and links[1].retries > 0
    for driver in (socket_driver, line_driver):
        driver.close()


def relayed_to(port: int, opened: list[socket.socket]) -> Callable[[], Exchange]:
    """Connections whose frames are relayed to a Modbus TCP server on 127.0.0.1:``port``,
    each answered with the whole answer frame it sends back (their sockets: ``opened``)."""
    def connect() -> Exchange:
        peer = socket.create_connection(("127.0.0.1", port), timeout=ANSWER_S)
        opened.append(peer)

        def exchange(frame: bytes) -> tuple[bytes, bool]:
            peer.sendall(frame)
            answer = b""
            while len(answer) < 6 or len(answer) < 6 + struct.unpack_from(">H", answer, 4)[0]:
                chunk = peer.recv(260)
                if not chunk:
                    return answer, True
                answer += chunk
            return answer, False
        return exchange
    return connect


def test_the_in_process_line_speaks_to_pymodbuss_server():
    opened: list[socket.socket] = []
    with PymodbusBench(CONFIG, total_va=420.0, level=60.0) as bench:
        link = ModbusLink(parse_bus_url(bench.url), TIMEOUT_S, 2,
                          InProcessLine(relayed_to(bench.port, opened), TIMEOUT_S))
        driver = ModbusBenchDriver(link, CONFIG.map)
        assert driver.read_power()["total_va"] == pytest.approx(420.0, abs=1.0)
        assert all(q == pytest.approx(60.0, abs=1.0) for q in driver.read_levels().values())
        relay = next(iter(CONFIG.map.relays))
        assert driver.write_relay(relay, True)[relay] is True
        assert bench.relays()[relay] is True  # as pymodbus holds it, read on a socket
        assert (link.connections, link.retries, link.line.discarded) == (1, 0, 0)
        driver.close()
        for peer in opened:
            peer.close()
