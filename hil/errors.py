"""Errors that reach the user as one clear line (the CLI prints them without a traceback)."""

from __future__ import annotations

from typing import Any


class HilError(Exception):
    """Base of every error hil reports to the user by message alone. ``result``: what the run
    this error ended did so far (its KPIs, ``status`` and session), for its report; None when
    the error came before a run started."""

    result: Any = None  # a hil.core.run.RunResult (typed loosely: errors import nothing)
    exit_status = 2     # what the command line exits with after this error's one line


class ConfigError(HilError):
    """A configuration file or value is wrong; the message names the key and the problem."""


class UsageError(HilError):
    """A command-line argument is wrong in a way argparse cannot see."""


class SessionFileError(HilError):
    """A session file cannot be read (missing, not MCAP, nothing recoverable)."""


class SafetyStopError(HilError):
    """A safety limit stopped the run; the hardware was put in its safe state first (exit 2)."""


class RecordingError(HilError):
    """The session cannot be recorded (disk full, writer gone, a write error): the run stops
    the hardware safely; the message names the cause and how much was recorded (exit 2)."""


class ForeignMasterError(HilError):
    """Another master drives the same hardware (found on the wire, or by the device lock):
    the run refuses or stops, outputs in their safe state (exit 2)."""


class RunInterruptedError(HilError):
    """A signal (Ctrl-C, SIGTERM) stopped the run; the hardware is in its safe state and the
    session finished with the KPIs so far. ``exit_status`` is 128 + the signal's number
    (130 for Ctrl-C, 143 for SIGTERM), as a shell reports a process a signal ended."""

    def __init__(self, message: str, exit_status: int) -> None:
        super().__init__(message)
        self.exit_status = exit_status


class ControllerError(HilError):
    """A controller raised, returned something that is not a command, or took too long; the
    run stops with the hardware in its safe state."""
