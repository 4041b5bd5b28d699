"""The serial number (0x1018:4) a ``hil emulate drive`` process gives its drives: its own,
by which a master tells them from the drives of an earlier process at the same URL."""

from __future__ import annotations

from hil.emulation import with_serial
from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.twin import drive_dictionary
from hil.protocols.cia301 import IDENTITY


def serial_of(config: DriveEmulatorConfig) -> int:
    serial: int = drive_dictionary(config).od[IDENTITY][4].default
    return serial


def test_an_emulator_process_answers_its_own_serial_number():
    assert serial_of(DriveEmulatorConfig(node_id=3)) == 3  # in process: the node id
    assert serial_of(with_serial(DriveEmulatorConfig(node_id=3), 0x5A5A5A83)) == 0x5A5A5A83


def test_a_serial_number_the_user_sets_is_kept():
    config = DriveEmulatorConfig(object_values=(((IDENTITY, 4), 4711),))
    assert serial_of(with_serial(config, 0x5A5A5A81)) == 4711
