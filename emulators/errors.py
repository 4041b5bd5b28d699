"""The emulators' errors, all :class:`~hil.errors.HilError` (one line each at the command
line)."""

from __future__ import annotations

from hil.errors import ConfigError, HilError


class EmulatorError(HilError):
    """An emulator cannot start or serve (an address in use, no such serial port)."""


class EmulatorSetupError(EmulatorError, ConfigError):
    """An emulator's setting is wrong (its plant, its faults); the message names it."""
