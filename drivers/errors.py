"""The drivers' errors, all :class:`~hil.errors.HilError` (one line each at the command line).
Each transport refines :class:`DriverError`: the relay bench's in :mod:`hil.drivers.bench.modbus`,
the drive's in :mod:`hil.drivers.canopen.errors`."""

from __future__ import annotations

from hil.errors import ConfigError, ForeignMasterError, HilError

__all__ = ["DriverError", "DriverSetupError", "ForeignMasterError"]


class DriverError(HilError):
    """The hardware, or the link to it, did not do what the driver asked."""


class DriverSetupError(DriverError, ConfigError):
    """A driver's setting is wrong (a URL, a port, a node, a value to write); the message names
    it and its unit."""
