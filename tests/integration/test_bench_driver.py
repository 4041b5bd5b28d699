"""The bench driver against the emulator: URLs, register map, lockstep reads, verified writes,
retries and reconnection, and the one-line errors for garbage."""

from __future__ import annotations

import numpy as np
import pytest

from hil.bench.config import load_bench_config, parse_bench_config
from hil.bench.emulated import make_emulator
from hil.core.config import deep_merge
from hil.drivers.bench.modbus import (
    DeviceError,
    LinkError,
    ModbusBenchDriver,
    ModbusLink,
    parse_bus_url,
    plan_reads,
)
from hil.emulators.null_modem import NullModem
from hil.errors import ConfigError
from tests.pymodbus_bench import ANSWER_S

pytestmark = [pytest.mark.timeout(60), pytest.mark.slow]

CONFIG = load_bench_config()


def test_bus_urls():
    tcp = parse_bus_url("modbus-tcp://127.0.0.1:5020")
    assert (tcp.kind, tcp.host, tcp.port) == ("tcp", "127.0.0.1", 5020)
    rtu = parse_bus_url("modbus-rtu:///dev/pts/7?baud=9600&parity=E&stopbits=1")
    assert (rtu.kind, rtu.device, rtu.baudrate, rtu.parity) == ("rtu", "/dev/pts/7", 9600, "E")
    assert parse_bus_url("modbus-rtu:///dev/ttyUSB0").baudrate == 115200
    assert parse_bus_url(rtu.url) == rtu and parse_bus_url(tcp.url) == tcp


@pytest.mark.parametrize(("url", "why"), [
    ("modbus-tcp://localhost", "no port"),
    ("modbus-tcp://:502", "no host"),
    ("modbus-tcp://host:99999", "bad port"),
    ("modbus-tcp://host:502/x?y=1", "no path or query"),
    ("modbus-rtu://dev/ttyS0", "names a device path"),
    ("modbus-rtu:///dev/ttyS0?baud=fast", "must be integers"),
    ("modbus-rtu:///dev/ttyS0?parity=X", "parity N|E|O"),
    ("modbus-rtu:///dev/ttyS0?speed=9600", "unknown option 'speed'"),
    ("http://example.com", "unknown scheme 'http'"),
    ("garbage", "not a URL"),
    ("", "not a URL"),
])
def test_malformed_urls_are_one_clear_error(url, why):
    with pytest.raises(ConfigError) as err:
        parse_bus_url(url)
    message = str(err.value)
    assert why in message and repr(url) in message and "\n" not in message
    assert "modbus-tcp://HOST:PORT" in message  # says what is expected


@pytest.mark.parametrize(("override", "why"), [
    ({"relays": {"P2": {"coil": 2}}}, "relays P1 and P2 are both on coil 2"),
    ({"relays": {"M1": {"coil": -1}}}, "coil must be >= 0"),
    ({"relays": {"M1": {"dwell_s": "long"}}}, "key 'relays.M1.dwell_s' must be a number"),
    ({"units": {"meter": 300}}, "key 'units.meter' must be 1..247"),
    ({"meter": {"registers": {"va_l1": 0x0001}}}, "overlaps"),
    ({"meter": {"poll": ["va_l9"]}}, "unknown: ['va_l9']"),
    ({"meter": {"max_registers_per_request": 500}}, "must be 2..125"),
    ({"levels": {"registers": {"q1": "zero"}}}, "key 'levels.registers.q1' must be an integer"),
])
def test_wrong_map_in_the_config_is_one_clear_error(override, why):
    with pytest.raises(ConfigError) as err:
        parse_bench_config(deep_merge(CONFIG.data, override))
    assert why in str(err.value) and "\n" not in str(err.value)


def test_reads_are_planned_within_the_meter_limit():
    full = CONFIG.map
    assert [(first, count) for first, count, _ in full.meter_reads] == [(0, 76)]
    few = plan_reads({"a": 0x00, "b": 0x02, "c": 0x38, "d": 0x3A}, max_count=80, max_gap=8)
    assert [(first, count) for first, count, _ in few] == [(0x00, 4), (0x38, 4)]
    capped = plan_reads({f"x{i}": 2 * i for i in range(50)}, max_count=80, max_gap=8)
    assert [(first, count) for first, count, _ in capped] == [(0, 80), (80, 20)]


@pytest.fixture(params=["tcp", "rtu"])
def rig(request):
    emulator = make_emulator(CONFIG)
    modem = None
    if request.param == "tcp":
        url = emulator.serve_tcp()
    else:
        modem = NullModem()
        emulator.serve_serial(modem.ports[1])
        url = f"modbus-rtu://{modem.ports[0]}?baud=115200"
    # every test of this rig expects its answers: waited for as long as a busy machine may
    # take (returned as soon as they are there); 0.2 s once went by unanswered over the
    # pseudo-terminal on a loaded fresh-clone suite
    link = ModbusLink(parse_bus_url(url), timeout_s=ANSWER_S, attempts=2)
    driver = ModbusBenchDriver(link, CONFIG.map)
    yield emulator, driver
    driver.close()
    emulator.stop()
    if modem is not None:
        modem.close()


def test_lockstep_reads_are_exactly_the_step_snapshot(rig):
    emulator, driver = rig
    driver.write_relay("M2", True)
    seen = set()
    for _ in range(20):
        expected = emulator.step()
        power, levels = driver.read_power(), driver.read_levels()
        assert power == {k: float(np.float32(v)) for k, v in expected.meter.items()}
        assert levels == {k: float(np.float32(v)) for k, v in expected.levels.items()}
        seen.add(power["va_l2"])
    assert len(seen) == 20                                 # a new snapshot every step


def test_relay_writes_are_verified_and_reach_the_plant(rig):
    emulator, driver = rig
    states = driver.write_relay("P2", True)
    assert states == {"M1": False, "M2": False, "P1": False, "P2": True}
    assert emulator.plant.coils()[3] is True
    assert driver.write_relay("P2", False)["P2"] is False
    assert driver.read_relays() == dict.fromkeys(("M1", "M2", "P1", "P2"), False)


def test_unknown_unit_over_tcp_is_one_clear_error():
    bench_map = parse_bench_config(deep_merge(CONFIG.data, {"units": {"meter": 9}})).map
    with make_emulator(CONFIG) as emulator:
        emulator.serve_tcp()
        # patient: the units that exist answer however loaded the machine; unit 9's 0x0B
        # comes at once
        driver = ModbusBenchDriver(ModbusLink(parse_bus_url(emulator.url), ANSWER_S, 1),
                                   bench_map)
        with pytest.raises(LinkError) as err:  # 0x0B: a gateway's "no answer", like RTU silence
            driver.probe()
        driver.close()
    message = str(err.value)
    assert "bench meter (unit 9)" in message and "exception 0x0b" in message
    assert "gateway target device failed to respond" in message and "\n" not in message


def test_a_device_exception_is_not_retried(rig):
    _emulator, driver = rig
    with pytest.raises(DeviceError) as err:
        driver.link.read_floats(driver.map.units["meter"], 0x0001, 2)   # splits a float
    assert err.value.code == 2 and "illegal data address" in str(err.value)


def test_unknown_unit_over_rtu_is_a_clear_timeout():
    bench_map = parse_bench_config(deep_merge(CONFIG.data, {"units": {"levels": 7}})).map
    with NullModem() as modem, make_emulator(CONFIG) as emulator:
        emulator.serve_serial(modem.ports[1])
        # patient enough that the units that exist answer on a loaded machine: only unit 7's
        # silence is timed out (0.1 s once lost unit 1's answer under load)
        link = ModbusLink(parse_bus_url(f"modbus-rtu://{modem.ports[0]}"), 0.5, 2)
        driver = ModbusBenchDriver(link, bench_map)
        with pytest.raises(LinkError) as err:
            driver.probe()
        driver.close()
    message = str(err.value)
    assert "bench levels (unit 7)" in message and "after 2 attempt(s)" in message
    assert "is the unit id right?" in message and "\n" not in message


def test_the_driver_retries_across_a_server_restart():
    with make_emulator(CONFIG) as first:
        first.serve_tcp()
        port = first.port
        link = ModbusLink(parse_bus_url(first.url), timeout_s=ANSWER_S, attempts=2)
        driver = ModbusBenchDriver(link, CONFIG.map)
        assert driver.read_levels() == {"q1": 55.0, "q2": 65.0}
    with make_emulator(CONFIG) as second:
        second.serve_tcp(port=port)
        second.plant.set_relay("P1", True)
        for _ in range(100):
            second.plant.step()
        # first attempt hits the dead connection, the second reconnects: no error surfaces
        assert driver.read_levels() == {"q1": 60.0, "q2": 65.0}
        assert link.connections == 2
    with pytest.raises(LinkError) as err:
        driver.read_levels()                               # nobody listening any more
    assert "after 2 attempt(s)" in str(err.value)
    driver.close()
