"""How the servo application reaches its drive: the drive URL schemes, and the emulated drive
wired in lockstep (the driver knows nothing of the emulator).

* ``emulated`` - :class:`EmulatedDrive`, the drive emulator on a private python-can virtual bus,
  pumped by the master after each transmission: the SYNC count is the plant's clock, so a run is
  deterministic and as fast as the CPU allows;
* ``socketcand://HOST:PORT[/CHANNEL]`` - a socketcand gateway (or ``hil emulate drive``);
* ``INTERFACE://CHANNEL`` - any python-can interface (``socketcan://can0``, ``pcan://...``);
* installed packages add schemes through the ``hil.drive_devices`` entry points.

A drive factory is called as ``factory(url, drive_config, on_event=sink)`` and returns a
:class:`~drivers.can_drive.CanDriveMaster` (not started).
"""

from __future__ import annotations

import os
from dataclasses import replace

from can.interfaces import VALID_INTERFACES

from drivers.can_drive import CanDriveMaster, DriveMasterConfig, open_interface, open_socketcand
from emulators.drive.node import DriveEmulatorConfig, LockstepDrive
from hil.core.errors import ConfigError
from hil.core.registry import Factory, SchemeRegistry, scheme_of
from hil.core.types import EventSink, no_event
from hil.servo.config import DriveConfig, load_drive_config

EXPECTED = "expected emulated, socketcand://HOST:PORT or INTERFACE://CHANNEL (python-can)"


class EmulatedDrive(CanDriveMaster):
    """A master whose drive is the emulator (``emulator``, a
    :class:`~emulators.drive.node.LockstepDrive`) on a private virtual bus, in lockstep. The
    emulated node takes the master's node id."""

    def __init__(self, master: DriveMasterConfig, emulator: DriveEmulatorConfig, *,
                 on_event: EventSink = no_event) -> None:
        self.emulator = LockstepDrive(replace(emulator, node_id=master.node_id))
        super().__init__(self.emulator.master_bus, master, on_event=on_event, timebase="cycles",
                         pump=self.emulator.pump, closers=(self.emulator.close,),
                         url="emulated")


def emulated_drive(url: str, drive: DriveConfig, *,
                   on_event: EventSink = no_event) -> EmulatedDrive:
    """``emulated``: the drive emulator in lockstep, with drive.toml's ``[emulator]``."""
    return EmulatedDrive(drive.master, drive.emulator, on_event=on_event)


def socketcand_drive(url: str, drive: DriveConfig, *,
                     on_event: EventSink = no_event) -> CanDriveMaster:
    """``socketcand://HOST:PORT[/CHANNEL]``."""
    return open_socketcand(url, drive.master, on_event=on_event)


def interface_drive(url: str, drive: DriveConfig, *,
                    on_event: EventSink = no_event) -> CanDriveMaster:
    """``INTERFACE://CHANNEL`` for a python-can interface."""
    return open_interface(url, drive.master, on_event=on_event)


def _python_can_interface(scheme: str) -> Factory | None:
    return interface_drive if scheme in VALID_INTERFACES else None


DRIVES = SchemeRegistry(
    "drive",
    {"emulated": ("hil.servo.rig", "emulated_drive"),
     "socketcand": ("hil.servo.rig", "socketcand_drive")},
    "hil.drive_devices",
    fallback=_python_can_interface,
)


def open_drive(url: str = "emulated", drive: DriveConfig | None = None, *,
               on_event: EventSink = no_event, realtime: bool = False) -> CanDriveMaster:
    """A master (not started) for the drive at ``url``, with ``drive`` (default: the packaged
    drive.toml). An unknown scheme is a ConfigError naming the known ones.

    ``emulated`` with ``realtime``: the drive emulator in a process of its own on loopback, as
    the hardware would be (the loop process then measures only its own cost), reading the same
    config file; the process stops when the master disconnects."""
    drive = drive or load_drive_config()
    if realtime and scheme_of(url) == "emulated":
        return emulator_process_drive(drive, on_event)
    try:
        factory = DRIVES.factory(url)
    except ConfigError as exc:
        raise ConfigError(f"{exc}; {EXPECTED}") from None
    master: CanDriveMaster = factory(url, drive, on_event=on_event)
    return master


def emulator_process_drive(drive: DriveConfig, on_event: EventSink) -> CanDriveMaster:
    """A master on socketcand to ``hil emulate drive`` started for it (node id of the master)."""
    from hil.emulator_process import start_drive_emulator

    path = drive.source if os.path.isfile(drive.source) else None
    process = start_drive_emulator(path, node=drive.master.node_id)
    on_event("emulator.process", f"drive emulator in process {process.pid} at {process.url}",
             source="drive", pid=process.pid, url=process.url)
    try:
        return open_socketcand(process.url, drive.master, on_event=on_event,
                               closers=(process.stop,))
    except BaseException:
        process.stop()
        raise
