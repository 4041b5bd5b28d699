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

from hil.errors import HilError


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


def output_problem(path: str) -> str | None:
    """Why a file cannot be written at ``path`` (None: it can): its missing folders are
    created here; a path that is a folder, lies below a file or in a folder that cannot be
    created or written is named. The command line's ``output_file`` and :func:`claim_output`
    both ask this."""
    if os.path.isdir(path):
        return f"{path} is a folder: give a file name in it"
    folder = os.path.dirname(os.path.abspath(path))
    existing = folder
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        return f"{path}: {existing} is a file, not a folder"
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        return f"{path}: cannot create the folder {folder}: {exc.strerror}"
    if not os.access(folder, os.W_OK):
        return f"{path}: the folder {folder} is not writable"
    return None


def open_locked(path: str, flags: int, mode: int) -> int | None:
    """``path`` opened (``O_CREAT`` and ``O_CLOEXEC`` added) and locked exclusively without
    waiting: its descriptor, or None when another process holds the lock. The lock goes with
    the descriptor, and with the process however it ends."""
    fd = os.open(path, flags | os.O_CREAT | os.O_CLOEXEC, mode)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def claim_output(path: str) -> OutputClaim:
    """Check that ``path`` can be written and lock it for this run; a clear
    :class:`OutputError` otherwise."""
    problem = output_problem(path)
    if problem is not None:
        raise OutputError(f"session file {problem}")
    created = not os.path.exists(path)
    try:
        fd = open_locked(path, os.O_WRONLY, 0o644)
    except OSError as exc:
        raise OutputError(f"session file {path}: cannot write it: {exc.strerror}") from None
    if fd is None:
        raise OutputError(f"session file {path} is being written by another run: give this "
                          "run another --out")
    return OutputClaim(path, fd, created)
