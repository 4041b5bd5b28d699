"""The session file, claimed for one run before any device is opened.

:func:`claim_output` checks that the session can be written where it is asked to go (the
folder created, the path not a folder, the file writable) and takes an exclusive lock on it
(``flock``), held until the session is closed: a second run given the same file refuses at
once, before it reaches its hardware, instead of mixing its data into the first one's.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from dataclasses import dataclass

from hil.core.errors import HilError


class OutputError(HilError):
    """The session file cannot be written, or another run is writing it (exit 2)."""


@dataclass
class OutputClaim:
    """A session file held for one run: its lock, and whether the run created it."""

    path: str
    fd: int | None
    created: bool

    def release(self) -> None:
        """Give the lock up (the session is closed)."""
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def abandon(self) -> None:
        """The run ended before its session started: the file goes, if this run made it."""
        if self.created and self.fd is not None:
            with contextlib.suppress(OSError):
                os.remove(self.path)
        self.release()


def claim_output(path: str) -> OutputClaim:
    """Check that ``path`` can be written and lock it for this run; a clear
    :class:`OutputError` otherwise."""
    folder = os.path.dirname(os.path.abspath(path))
    existing = folder
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        raise OutputError(f"session file {path}: {existing} is a file, not a folder")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"session file {path}: cannot create its folder {folder}: "
                          f"{exc.strerror}") from None
    if os.path.isdir(path):
        raise OutputError(f"session file {path}: is a folder; give a file name, e.g. "
                          f"{os.path.join(path, 'run.mcap')}")
    created = not os.path.exists(path)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        raise OutputError(f"session file {path}: cannot write it: {exc.strerror}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise OutputError(f"session file {path} is being written by another run: give this "
                          "run another --out") from None
    return OutputClaim(path, fd, created)
