"""Opening drives by URL (hil/servo/rig.py): the scheme registry, python-can interfaces as the
fallback, and the emulated drive wired in by the application, not by the driver."""

import pytest

from drivers.can_drive import CanDriveMaster, DriveLinkLostError
from hil.core.errors import ConfigError
from hil.core.types import Device
from hil.servo.config import load_drive_config
from hil.servo.rig import DRIVES, EmulatedDrive, interface_drive, open_drive, socketcand_drive


@pytest.mark.parametrize("url", ["nowhere", "modbus-tcp://127.0.0.1:5020", "can0"])
def test_an_unknown_scheme_is_a_config_error_listing_the_known_ones(url):
    with pytest.raises(ConfigError) as error:
        open_drive(url)
    message = str(error.value)
    assert message.startswith(f"drive '{url}': unknown scheme")
    assert "(known: emulated, socketcand" in message and "INTERFACE://CHANNEL" in message


def test_schemes_resolve_to_their_factories():
    assert DRIVES.factory("socketcand://127.0.0.1:29536/can0") is socketcand_drive
    for url in ("virtual://bus", "pcan://PCAN_USBBUS1", "socketcan://can0"):
        assert DRIVES.factory(url) is interface_drive  # any python-can interface
    assert {"emulated", "socketcand"} <= set(DRIVES.schemes())


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


def test_a_python_can_interface_url_opens_a_master_on_that_bus():
    master = open_drive("virtual://rig-test")
    try:
        assert type(master) is CanDriveMaster and master.url == "virtual://rig-test"
    finally:
        master.close()
    with pytest.raises(ConfigError, match="expected INTERFACE://CHANNEL"):
        open_drive("virtual://")
    with pytest.raises(DriveLinkLostError, match="cannot open CAN interface 'pcan'"):
        open_drive("pcan://PCAN_USBBUS1")
