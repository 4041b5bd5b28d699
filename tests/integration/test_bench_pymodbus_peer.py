"""The bench driver against a Modbus server hil did not write: pymodbus's own TCP server with
its own datastore (coils of the relay module, float32 input registers of the meter and the
level sensors, high word first), in a thread of this process on loopback."""

import asyncio
import socket
import struct
import threading

import pytest
from pymodbus.datastore import (
    ModbusDeviceContext,
    ModbusSequentialDataBlock,
    ModbusServerContext,
)
from pymodbus.server import ModbusTcpServer

from hil.bench.config import load_bench_config
from hil.drivers.bench.modbus import ModbusBenchDriver, ModbusLink, parse_bus_url

pytestmark = [pytest.mark.slow]

CONFIG = load_bench_config(None)


def words(values):
    """float32 big-endian, high word first, as 16-bit registers."""
    return list(struct.unpack(f">{2 * len(values)}H", struct.pack(f">{len(values)}f", *values)))


def free_port():
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture
def peer():
    bench_map = CONFIG.map
    first, end = CONFIG.server.meter_space
    meter = [0.0] * ((end - first) // 2)
    expected = {}
    for k, (name, address) in enumerate(CONFIG.server.meter_registers.items()):
        meter[(address - first) // 2] = expected[name] = 100.0 + 7.25 * k
    levels = [55.5, 123.25]
    coils = [False] * 8
    # pymodbus's datastore addresses data from 1 (the Modbus data model), so a block served
    # from protocol address 0 starts at 1
    devices = {
        CONFIG.server.units["relays"]: ModbusDeviceContext(
            co=ModbusSequentialDataBlock(1, coils)),
        CONFIG.server.units["meter"]: ModbusDeviceContext(
            ir=ModbusSequentialDataBlock(first + 1, words(meter))),
        CONFIG.server.units["levels"]: ModbusDeviceContext(
            ir=ModbusSequentialDataBlock(1, words(levels))),
    }
    port = free_port()
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    servers = []

    async def start():
        server = ModbusTcpServer(ModbusServerContext(devices=devices, single=False),
                                 address=("127.0.0.1", port))
        await server.serve_forever(background=True)
        servers.append(server)

    def serve():
        asyncio.set_event_loop(loop)
        loop.run_until_complete(start())
        ready.set()
        loop.run_forever()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    assert ready.wait(5)
    driver = ModbusBenchDriver(ModbusLink(parse_bus_url(f"modbus-tcp://127.0.0.1:{port}"),
                                          0.5, 2), bench_map)
    yield driver, expected, dict(zip(bench_map.level_names, levels, strict=True))
    driver.close()
    asyncio.run_coroutine_threadsafe(servers[0].shutdown(), loop).result(5)
    loop.call_soon_threadsafe(loop.stop)
    thread.join(5)


def test_the_driver_reads_the_meter_and_levels_of_pymodbuss_server(peer):
    driver, meter, levels = peer
    power = driver.read_power()
    assert set(power) == set(driver.map.meter_quantities)
    for name in power:
        assert power[name] == pytest.approx(meter[name])
    assert driver.read_levels() == pytest.approx(levels)


def test_the_driver_switches_and_reads_back_the_relays_of_pymodbuss_server(peer):
    driver, _, _ = peer
    assert not any(driver.read_relays().values())
    driver.write_relay("P1", True)
    assert driver.read_relays()["P1"] is True
    driver.write_relay("P1", False)
    assert driver.read_relays()["P1"] is False
