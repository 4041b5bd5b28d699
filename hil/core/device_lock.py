"""One master at a time: an exclusive lock per device URL on this machine.

A run locks the bench or bus it drives (:func:`lock_device`) before opening it, and holds the
lock until it has closed it; a second run (or ``hil drive reset``) on the same URL refuses at
once with one line naming the run that holds it. The locks are ``flock`` locks on files in
:func:`lock_folder` (``HIL_LOCK_DIR``, default ``/tmp/hil-locks``): the kernel drops them
when their process ends, however it ends, so a crashed run never leaves a stale lock.

Another master on the wire that is not a hil run on this machine is for the protocol to
reveal: see :class:`hil.drivers.bench.safe_bench.SafeBench` (relays switched by someone else) and
:mod:`hil.drivers.canopen.master` (a foreign SYNC producer).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile

from hil.core.recording.output import open_locked
from hil.errors import ForeignMasterError, HilError

LOCK_DIR_ENV = "HIL_LOCK_DIR"


def lock_folder() -> str:
    """Where the device locks live (created, open to every user, sticky like /tmp)."""
    folder = os.environ.get(LOCK_DIR_ENV) or os.path.join(tempfile.gettempdir(), "hil-locks")
    if not os.path.isdir(folder):
        try:
            os.makedirs(folder, exist_ok=True)
            os.chmod(folder, 0o1777)
        except OSError as exc:
            raise HilError(f"cannot create the device lock folder {folder}: {exc.strerror} "
                           f"(set {LOCK_DIR_ENV} to a writable folder)") from None
    return folder


class DeviceLock:
    """The lock of one device URL, held by this process until :meth:`release`."""

    def __init__(self, url: str, fd: int) -> None:
        self.url = url
        self._fd: int | None = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> DeviceLock:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.release()


def lock_device(url: str, what: str = "device") -> DeviceLock:
    """Lock ``url`` for this process; :class:`ForeignMasterError` when another run holds it."""
    key = url.strip().rstrip("/").lower()
    name = hashlib.sha256(key.encode()).hexdigest()[:24] + ".lock"
    path = os.path.join(lock_folder(), name)
    try:
        fd = open_locked(path, os.O_RDWR, 0o666)
    except OSError as exc:
        raise HilError(f"cannot lock {what} {url}: {path}: {exc.strerror}") from None
    if fd is None:
        holder = ""
        with contextlib.suppress(OSError), open(path, encoding="utf-8",
                                                 errors="replace") as file:
            holder = file.readline().strip()
        raise ForeignMasterError(f"{what} {url} is in use by another hil run "
                                 f"({holder or 'unknown process'}): one master at a time")
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"pid {os.getpid()}\n{url}\n".encode(), 0)
    return DeviceLock(url, fd)
