"""The labgrid drivers of hil: a target's bench or drive, opened through hil's safety layer
while the driver is active (``target.activate(driver)``, or ``target.get_driver(...)``), and
put in its safe state when it is deactivated (relays at their safe levels; the drive
quick-stopped and out of OPERATION ENABLED)."""

from __future__ import annotations

import contextlib
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import attr
from labgrid.driver import Driver
from labgrid.factory import target_factory

if TYPE_CHECKING:
    from hil.drivers.bench.safe_bench import SafeBench
    from hil.drivers.canopen import CanDriveMaster


@attr.s(eq=False)
class _OpenedWhileActive(Driver):
    """A device entered as a context manager on activation, left on deactivation."""

    def __attrs_post_init__(self) -> None:
        super().__attrs_post_init__()
        self._stack = contextlib.ExitStack()
        self._device: Any = None

    def _open(self) -> contextlib.AbstractContextManager[Any]:
        raise NotImplementedError

    def on_activate(self) -> None:
        self._device = self._stack.enter_context(self._open())

    def on_deactivate(self) -> None:
        self._device = None
        self._stack.close()


@target_factory.reg_driver
@attr.s(eq=False)
class HilBenchDriver(_OpenedWhileActive):
    """The bench of a ``HilBench`` resource; ``bench`` is hil's safety layer over it
    (:class:`hil.drivers.bench.safe_bench.SafeBench`: ``read_levels()``, ``set_relay()``...)."""

    bindings = {"resource": "HilBench"}  # noqa: RUF012 (labgrid reads it from the class)

    def _open(self) -> contextlib.AbstractContextManager[Any]:
        from hil import api

        return api.open_bench(self.resource.url, self.resource.config or None)

    @property
    @Driver.check_active
    def bench(self) -> SafeBench:
        return self._device  # type: ignore[no-any-return]


@target_factory.reg_driver
@attr.s(eq=False)
class HilDriveDriver(_OpenedWhileActive):
    """The drive of a ``HilDrive`` resource; ``master`` is hil's CiA 402 master, opened and
    configured (not enabled)."""

    bindings = {"resource": "HilDrive"}  # noqa: RUF012 (labgrid reads it from the class)

    def _open(self) -> contextlib.AbstractContextManager[Any]:
        return open_drive_resource(self.resource.url, self.resource.node, self.resource.eds,
                                   self.resource.config)

    @property
    @Driver.check_active
    def master(self) -> CanDriveMaster:
        return self._device  # type: ignore[no-any-return]


@contextlib.contextmanager
def open_drive_resource(url: str, node: int, eds: str, config: str) -> Any:
    """The drive of a ``HilDrive``'s fields, opened and configured (not enabled);
    quick-stopped, disabled and released on exit."""
    from hil.servo.config import load_drive_config
    from hil.servo.rig import open_drive

    drive = load_drive_config(config or None)
    master_config = drive.master
    if node:
        master_config = replace(master_config, node_id=node)
    if eds:
        master_config = replace(master_config, eds=eds)
    master = open_drive(url, replace(drive, master=master_config))
    try:
        master.open()
        master.configure()
        yield master
    finally:
        master.close()
