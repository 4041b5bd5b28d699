"""The session file, claimed for one run before any device is opened, and put in place only
once the run has started.

:func:`claim_output` checks that the session can be written where it is asked to go (the
folder created, the path neither a folder nor a device, FIFO or socket) and opens a staging
file beside it, ``.NAME.starting``. The session is written there until its loop starts
(:meth:`OutputClaim.start`), which renames it to ``NAME``, replacing what was there. A run
that ends before (a device that does not answer, a controller that cannot be built, a drive
that refuses its settings) removes its staging file and nothing else: the path is left as it
was, an earlier session there included. hil removes only the files it created.

Both files are locked (``flock``, exclusive) until the session is closed: a second run given
the same file refuses at once, before it reaches its hardware, instead of mixing its data into
the first one's or replacing it. The staging file's lock goes with the session's writer
process too (it inherits the descriptor), which removes the file itself when the loop process
dies before the run started.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import stat
import struct
from dataclasses import dataclass

from hil.errors import HilError

STAGING_SUFFIX = ".starting"
_MCAP_START = b"\x89MCAP0\r\n\x01"  # the magic, then a Header record's opcode
_STRING = struct.Struct("<I")


class OutputError(HilError):
    """The session file cannot be written, or another run is writing it (exit 2)."""


@dataclass
class OutputClaim:
    """A session file held for one run: the staging file it is written to until the run
    starts (open and locked), and the file found at ``path`` (locked while it may still be
    replaced)."""

    path: str
    staging: str
    fd: int | None
    held_fd: int | None = None
    started: bool = False

    def start(self) -> None:
        """The run has started: the staging file becomes the session at ``path``."""
        if self.started or self.fd is None:
            return
        os.replace(self.staging, self.path)
        self.started = True
        self._close_held()

    def release(self) -> None:
        """Give the locks up (the session is closed)."""
        self._close_held()
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def abandon(self) -> None:
        """The run ended before it started: its staging file goes, the path stays as it was."""
        if not self.started and self.fd is not None:
            remove_if_same(self.staging, os.fstat(self.fd))
        self.release()

    def _close_held(self) -> None:
        if self.held_fd is not None:
            os.close(self.held_fd)
            self.held_fd = None


def remove_if_same(path: str, identity: os.stat_result) -> None:
    """Remove ``path`` if it is still the file of ``identity`` (hil's own), nothing else."""
    with contextlib.suppress(OSError):
        if os.path.samestat(os.stat(path), identity):
            os.remove(path)


def series_file(path: str, index: int) -> str:
    """The name of file ``index`` of the split series of ``path``."""
    stem, ext = os.path.splitext(path)
    return f"{stem}_{index:03d}{ext or '.mcap'}"


def staging_path(path: str) -> str:
    """Where the session at ``path`` is written until its run starts: ``.NAME.starting``."""
    folder, name = os.path.split(path)
    return os.path.join(folder, f".{name}{STAGING_SUFFIX}")


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


def special_file(path: str) -> str | None:
    """What ``path`` is when it exists and is not a regular file (``a character device``,
    ``a FIFO``...); None otherwise."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    for test, kind in ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return None if stat.S_ISREG(mode) else "not a regular file"


def claim_output(path: str) -> OutputClaim:
    """Check that a session can be written at ``path``, open its staging file and lock both;
    a clear :class:`OutputError` otherwise. Nothing at ``path`` is changed."""
    problem = output_problem(path)
    if problem is not None:
        raise OutputError(f"session file {problem}")
    kind = special_file(path)
    if kind is not None:
        raise OutputError(f"session file {path} is {kind}: a session is a file of its own, "
                          "written then finished with its index; give a file path")
    target = os.path.realpath(path)  # through a link: the file it names is the session
    if os.path.exists(target) and not os.access(target, os.W_OK):
        raise OutputError(f"session file {path}: cannot write it: Permission denied")
    staging = staging_path(target)
    fd = _open_staging(path, staging)
    claim = OutputClaim(target, staging, fd)
    try:
        claim.held_fd = _lock_existing(path, target)
    except BaseException:
        claim.abandon()
        raise
    return claim


def _busy(path: str) -> OutputError:
    return OutputError(f"session file {path} is being written by another run: give this run "
                       "another --out")


def _locked(fd: int) -> bool:
    """Lock ``fd`` exclusively without waiting: False when another process holds it."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False
    return True


def open_locked(path: str, flags: int, mode: int) -> int | None:
    """``path`` opened (``O_CREAT`` and ``O_CLOEXEC`` added) and locked exclusively without
    waiting: its descriptor, or None when another process holds the lock. The lock goes with
    the descriptor, and with the process however it ends."""
    fd = os.open(path, flags | os.O_CREAT | os.O_CLOEXEC, mode)
    if not _locked(fd):
        os.close(fd)
        return None
    return fd


def _open_staging(path: str, staging: str) -> int:
    """The staging file, created (or a leftover of hil's taken over, emptied) and locked."""
    try:
        fd = os.open(staging, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644)
    except FileExistsError:
        fd = _take_over(path, staging)
    except OSError as exc:
        raise OutputError(f"session file {path}: cannot write it: {exc.strerror}") from None
    else:
        if not _locked(fd):  # created an instant ago: only a run racing this one holds it
            os.close(fd)
            raise _busy(path)
    return fd


def _take_over(path: str, staging: str) -> int:
    """A staging file already there: another run starting into ``path`` (it is locked), a
    leftover of a run whose processes all died (a session hil began: emptied and reused), or
    someone else's file (refused)."""
    try:
        fd = os.open(staging, os.O_RDWR | os.O_CLOEXEC)
    except OSError as exc:
        raise OutputError(f"session file {path}: cannot write {staging}: {exc.strerror}"
                          ) from None
    if not _locked(fd):
        os.close(fd)
        raise _busy(path)
    if not _begun_by_hil(os.pread(fd, 64, 0)):
        os.close(fd)
        raise OutputError(f"session file {path}: {staging} is in the way and is not a session "
                          "hil began: move it away")
    os.ftruncate(fd, 0)
    return fd


def _begun_by_hil(head: bytes) -> bool:
    """Whether ``head`` is the start of a session file hil's writer began (or nothing yet)."""
    if not head:
        return True
    if not head.startswith(_MCAP_START):
        return False
    try:  # Header: opcode, length, profile (string), library (string)
        at = len(_MCAP_START) + 8
        at += _STRING.size + _STRING.unpack_from(head, at)[0]
        size = _STRING.unpack_from(head, at)[0]
    except struct.error:
        return False
    return head[at + _STRING.size:at + _STRING.size + size] == b"hil"


def _lock_existing(path: str, target: str) -> int | None:
    """The file already at ``target``, opened and locked until this run replaces it; None
    when there is none."""
    try:
        fd = os.open(target, os.O_RDONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise OutputError(f"session file {path}: cannot read it: {exc.strerror}") from None
    if not _locked(fd):
        os.close(fd)
        raise _busy(path)
    return fd
