"""Opening drives by URL (hil/servo/rig.py, drivers/canopen/bus.py): the scheme registry, every
python-can interface by its own name (``_`` included), channels that are device paths, typed
options, the [bus] table, and the emulated drive wired in by the application, not the driver."""

import pytest

from hil.contracts import Device
from hil.drivers.canopen import CanBusSpec, CanDriveMaster, DriveLinkLostError, parse_can_url
from hil.errors import ConfigError
from hil.servo.config import AxisSpec, load_drive_config
from hil.servo.rig import (
    DRIVES,
    EmulatedDrive,
    can_drives,
    emulated_drives,
    open_drive,
    open_drives,
)


@pytest.mark.parametrize("url", ["nowhere", "modbus-tcp://127.0.0.1:5020", "can0"])
def test_an_unknown_scheme_is_a_config_error_listing_the_forms(url):
    with pytest.raises(ConfigError) as error:
        open_drive(url)
    message = str(error.value)
    assert message.startswith(f"drive '{url}': unknown scheme")
    assert "(known: emulated, ethercat, socketcand" in message and "INTERFACE://CHANNEL" in message


def test_schemes_resolve_to_their_factories():
    assert DRIVES.factory("emulated") is emulated_drives
    for url in ("socketcand://127.0.0.1:29536/can0", "virtual://bus", "pcan://PCAN_USBBUS1",
                "socketcan://can0", "udp_multicast://239.0.0.1", "gs_usb://0",
                "slcan:///dev/ttyACM0"):
        assert DRIVES.factory(url) is can_drives  # any python-can interface
    assert {"emulated", "socketcand"} <= set(DRIVES.schemes())


@pytest.mark.parametrize(("url", "spec"), [
    ("socketcan://can0", CanBusSpec("socketcan", "can0")),
    ("slcan:///dev/ttyACM0?bitrate=1000000",
     CanBusSpec("slcan", "/dev/ttyACM0", {"bitrate": 1000000})),
    ("serial:///dev/ttyUSB0", CanBusSpec("serial", "/dev/ttyUSB0")),
    ("gs_usb://0", CanBusSpec("gs_usb", "0")),
    ("udp_multicast://239.0.0.1?port=43113&ttl=0",
     CanBusSpec("udp_multicast", "239.0.0.1", {"port": 43113, "ttl": 0})),
    ("pcan://PCAN_USBBUS1?fd=true&f_clock_mhz=80&data_bitrate=2e6",
     CanBusSpec("pcan", "PCAN_USBBUS1", {"fd": True, "f_clock_mhz": 80,
                                         "data_bitrate": 2e6})),
    ("kvaser://0", CanBusSpec("kvaser", "0")),
    ("virtual://bench", CanBusSpec("virtual", "bench")),
    ("socketcand://10.0.0.5:29536/vcan1",
     CanBusSpec("socketcand", "vcan1", {"host": "10.0.0.5", "port": 29536})),
    ("socketcand://10.0.0.5:29536", CanBusSpec("socketcand", "can0",
                                               {"host": "10.0.0.5", "port": 29536})),
])
def test_url_forms_give_interface_channel_and_typed_options(url, spec):
    parsed = parse_can_url(url)
    assert parsed == spec
    assert parse_can_url(parsed.url) == spec  # and back


@pytest.mark.parametrize(("url", "problem"), [
    ("can_bus://0", "unknown scheme 'can_bus'.*python-can's: canalystii"),
    ("virtual://", "no channel"),
    ("virtual://x?bitrate", "key=value"),
    ("virtual://x?port=1&port=2", "'port' given twice"),
    ("virtual://x?channel=y", "the URL's own part"),
    ("socketcand://nowhere", "expected socketcand://HOST:PORT"),
])
def test_bad_urls_are_one_line_naming_the_problem(url, problem):
    with pytest.raises(ConfigError, match=problem) as error:
        open_drive(url)
    assert "\n" not in str(error.value)


def test_the_emulated_drive_is_a_device_on_the_masters_node_id():
    master = open_drive("emulated", load_drive_config(overrides={"master": {"node_id": 5}}))
    assert isinstance(master, EmulatedDrive) and isinstance(master, Device)
    assert master.url == "emulated" and master.emulator.node.node_id == 5
    master.open()
    master.configure()
    master.enable()
    assert master.receive_feedback().state == "OPERATION ENABLED" and master.link_up
    master.close()
    assert master.emulator.node.state == "SWITCH ON DISABLED"
    master.close()  # idempotent


def test_a_factory_opens_every_axis_of_its_bus_as_a_group():
    """Several axes on one bus: one master per node on one AxisBus, cycled together, one
    SYNC a cycle for all; the emulator (one node per axis) closes with the bus."""
    drive = load_drive_config()
    bus = open_drives("emulated", drive, [AxisSpec("x", 1, current_limit_ma=600.0),
                                          AxisSpec("y", 2)])
    x, y = bus.masters
    assert (x.node_id, y.node_id) == (1, 2) and bus.group is not None
    assert x.current_limit_ma == 600.0 and y.current_limit_ma == drive.master.current_limit_ma
    for master in bus.masters:
        master.open()
        master.configure()
        master.enable()
    bus.cycle_together(True)
    sent = bus.group.bus.link.syncs_sent
    for master in bus.masters:
        master.send_command(0.0)
    bus.end_cycle()
    assert bus.group.bus.link.syncs_sent == sent + 1
    assert [m.receive_feedback().state for m in bus.masters] == ["OPERATION ENABLED"] * 2
    bus.cycle_together(False)
    bus.disconnect()
    assert not x.enabled and not y.enabled


@pytest.mark.parametrize("url", ["virtual://rig-test", "udp_multicast://239.0.0.1?port=43199"])
def test_a_python_can_interface_url_opens_a_master_on_that_bus(url):
    master = open_drive(url)
    try:
        assert type(master) is CanDriveMaster and master.url == url
    finally:
        master.close()


def test_an_interface_that_cannot_open_is_one_line_with_python_cans_reason():
    with pytest.raises(DriveLinkLostError) as error:
        open_drive("pcan://PCAN_USBBUS1")
    message = str(error.value)
    assert message.startswith("cannot open CAN interface 'pcan' channel 'PCAN_USBBUS1': ")
    assert "\n" not in message and len(message) > 60


def test_the_bus_table_is_the_same_url_in_a_config_file(tmp_path):
    config = tmp_path / "drive.toml"
    config.write_text('[bus]\ninterface = "udp_multicast"\nchannel = "239.0.0.1"\n'
                      '[bus.options]\nport = 43198\n')
    drive = load_drive_config(config)
    assert drive.bus == CanBusSpec("udp_multicast", "239.0.0.1", {"port": 43198})
    assert drive.bus_url == "udp_multicast://239.0.0.1?port=43198"
    master = open_drive(None, drive)
    try:
        assert master.url == drive.bus_url
    finally:
        master.close()
    assert load_drive_config().bus is None  # the default: the emulated drive
    bad = tmp_path / "bad.toml"
    bad.write_text('[bus]\ninterface = "canbus"\n')
    with pytest.raises(ConfigError, match=r"bus\.interface"):
        load_drive_config(bad)
    bad.write_text('[bus]\ninterface = "socketcand"\n')
    with pytest.raises(ConfigError, match="needs host and port"):
        load_drive_config(bad)


@pytest.mark.parametrize(("path", "bus", "expected"), [
    ("frames.asc", 0, "frames.asc"), ("frames.asc", 1, "frames-bus2.asc"),
    ("logs.d/frames", 2, "logs.d/frames-bus3"), (None, 1, None)])
def test_each_bus_of_a_run_logs_to_its_own_file(path, bus, expected):
    from hil.servo.run import can_log_path

    assert can_log_path(path, bus) == expected
