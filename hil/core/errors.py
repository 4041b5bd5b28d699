"""Errors that reach the user as one clear line (the CLI prints them without a traceback)."""


class HilError(Exception):
    """Base of every error hil reports to the user by message alone."""


class ConfigError(HilError):
    """A configuration file or value is wrong; the message names the key and the problem."""


class UsageError(HilError):
    """A command-line argument is wrong in a way argparse cannot see."""


class SessionFileError(HilError):
    """A session file cannot be read (missing, not MCAP, nothing recoverable)."""



class ControllerError(HilError):
    """A controller raised, returned something that is not a command, or took too long; the
    run stops with the hardware in its safe state."""
