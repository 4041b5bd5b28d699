"""What goes wrong between the master and a drive, one class per kind (all HilErrors: one line
each)."""

from __future__ import annotations

from hil.drivers.errors import DriverError


class DriveError(DriverError):
    """The drive or the link to it is not in a state to be commanded."""


class DriveFaultError(DriveError):
    """The drive reports FAULT; ``emcy_code`` is its last error code (0 if unknown)."""

    def __init__(self, message: str, emcy_code: int = 0) -> None:
        super().__init__(message)
        self.emcy_code = emcy_code


class DriveLinkLostError(DriveError):
    """No answer from the drive (TPDO watchdog, SDO time-out, bus error, reboot)."""


class DriveNotFoundError(DriveLinkLostError):
    """The node never answered: no drive at that node id on that bus (a wrong ``--node``, the
    wrong bus, the drive off). The message names the nodes a scan of the bus found."""


class DriveGoneError(DriveLinkLostError):
    """In lockstep, the drive gave no sign of life for the whole wall-clock bound of a cycle:
    it is gone (stopped, disconnected, or paused for longer than the bound). A disturbed run,
    not a failed one: exit status 3."""

    exit_status = 3


class BusSharedError(DriveError):
    """Another master drives the bus (a SYNC, NMT command or heartbeat this one did not send)."""


class DriveStateError(DriveError):
    """The CiA 402 state machine is not where it should be (stuck, or left OPERATION ENABLED)."""



def one_line(exc: BaseException) -> str:
    """An exception's message on one line: python-can's socketcand interface appends
    ``traceback.format_exc()`` to its errors, which is cut off here."""
    text = str(exc).split("Traceback (most recent call last)")[0].strip()
    return " ".join(text.splitlines()[0].split()) if text else type(exc).__name__
