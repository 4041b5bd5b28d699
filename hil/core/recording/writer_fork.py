"""Writer processes forked from a small server, one per loop process, instead of started afresh.

A writer started as a fresh interpreter would cost each session about 0.1 s of CPU before it
is ready: the interpreter's start and the imports of mcap, zstandard and the encoders. The
fork server (``python -m hil.core.recording.writer_fork``) pays them once per loop process,
as a run command begins (else at its first session), and forks each writer from itself in a
few milliseconds: a process that records many sessions (a test suite, a script of runs, a
sweep run serially) pays them once (``benchmarks/session_start.py``). The server is small
and single-threaded, so its forks copy little and take no lock another thread held; the
loop's own process is never forked (its pages would turn copy-on-write under the loop).

Each writer is still the loop process's child, as a ``Popen``'s would be: the server forks
it through a short-lived intermediate process and the loop process is the writer's
*subreaper* (``PR_SET_CHILD_SUBREAPER``) for that moment, so the orphaned writer is given
to it. Its exit status, a kill and its ``pid`` then mean what they meant
(:class:`ForkedWriter`). It gets the loop process's record pipe, standard error, working
directory and passed descriptors over the server's socket (``SCM_RIGHTS``) under the same
numbers, runs in its own session, SCHED_OTHER on every usable core, with nothing else
open: :func:`hil.core.recording.writer.serve` then does the rest. Its user, environment,
resource limits and umask are the loop process's when the server started. The server ends
when the loop process closes its socket, and by the same token when the loop process ends.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import gc
import io
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from hil.core.libc import libc

PR_SET_CHILD_SUBREAPER = 36  # prctl(2)
PR_GET_CHILD_SUBREAPER = 37
REAP_POLL_S = 0.005          # how often a timed wait looks whether the writer has ended
REQUEST_BYTES = 1 << 16      # a request's JSON (options and descriptor numbers) at most
PR_SET_NAME = 15
#: what ``ps -o comm``, ``top`` and /proc/PID/comm call them (their command lines are the
#: server's: ``python -m hil.core.recording.writer_fork``)
WRITER_NAME = "hil writer"
SERVER_NAME = "hil writer fork"


class ForkedWriter:
    """A forked writer as the recorder uses a ``Popen``: ``pid``, ``stdin`` (its record
    stream), ``stdout`` (its words), ``poll``, ``wait``, ``kill`` and ``returncode``
    (negative: the signal that ended it)."""

    def __init__(self, pid: int, stdin: io.FileIO, stdout: io.FileIO) -> None:
        self.pid = pid
        self.stdin = stdin
        self.stdout = stdout
        self.returncode: int | None = None

    def poll(self) -> int | None:
        """The exit status once the writer has ended, else None."""
        if self.returncode is None:
            self._reap(os.WNOHANG)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        """Wait for the writer to end (``subprocess.TimeoutExpired`` after ``timeout`` s)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while (code := self.poll()) is None:
            if deadline is None:
                self._reap(0)
            elif time.monotonic() >= deadline:
                raise subprocess.TimeoutExpired(f"hil writer {self.pid}", timeout or 0.0)
            else:
                time.sleep(REAP_POLL_S)
        return code

    def kill(self) -> None:
        """SIGKILL the writer unless it has ended and been reaped."""
        if self.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGKILL)

    def _reap(self, flags: int) -> None:
        try:
            pid, status = os.waitpid(self.pid, flags)
        except ChildProcessError:  # reaped by others (SIGCHLD ignored): its status is lost
            self.returncode = 0
            return
        if pid:
            self.returncode = os.waitstatus_to_exitcode(status)


def start_writer(options: dict[str, Any], pass_fds: Sequence[int]) -> ForkedWriter:
    """The writer of ``options`` (the recorder's), forked by this process's server (started
    now unless :func:`start_server` did), ``pass_fds`` open in it under the same numbers."""
    with _LOCK:
        return _running_server().fork(options, pass_fds)


def start_server() -> None:
    """Start this process's fork server unless it runs, without waiting for it: a run command
    calls this as it begins (and a run before it opens its devices), so the server's start-up
    (an interpreter and the writer's imports, 0.1 s) goes on beside the run's own imports
    rather than before its first session. Best effort: a server that cannot start is
    reported by :func:`start_writer`, which tries again."""
    with _LOCK, contextlib.suppress(OSError):
        _running_server()


def _running_server() -> _Server:
    global _SERVER
    if _SERVER is None or not _SERVER.alive():
        if _SERVER is not None:  # killed, say: its writers run on, ours to reap
            _SERVER.socket.close()
        _SERVER = _Server()
    return _SERVER


class _Server:
    """The loop process's side of its fork server."""

    def __init__(self) -> None:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [root, env.get("PYTHONPATH")]))
        with theirs, _subreaper():  # its descendants look for a subreaper when orphaned
            self.process = subprocess.Popen(
                [sys.executable, "-m", __name__, str(theirs.fileno())], env=env,
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, pass_fds=[theirs.fileno()],
                start_new_session=True)
        self.socket = ours

    def alive(self) -> bool:
        return self.process.poll() is None

    def fork(self, options: dict[str, Any], pass_fds: Sequence[int]) -> ForkedWriter:
        stream_in, stream_out = os.pipe()
        said_in, said_out = os.pipe()
        here = os.open(".", os.O_RDONLY | os.O_DIRECTORY)
        request = json.dumps({"options": options, "pass_fds": list(pass_fds)}).encode()
        try:
            with _subreaper():
                socket.send_fds(self.socket, [request],
                                [stream_in, said_out, 2, here, *pass_fds])
                reply = self.socket.recv(64)
        finally:
            for fd in (stream_in, said_out, here):
                os.close(fd)
        if not reply.isdigit():
            os.close(stream_out)
            os.close(said_in)
            raise OSError(f"the writers' fork server failed ({reply.decode() or 'ended'})")
        return ForkedWriter(int(reply), open(stream_out, "wb", buffering=0),
                            open(said_in, "rb", buffering=0))


_LOCK = threading.Lock()
_SERVER: _Server | None = None


def _forget_server() -> None:
    """In a forked child of the loop process: its parent's server is not its own."""
    global _SERVER
    if _SERVER is not None:
        _SERVER.socket.close()
    _SERVER = None


os.register_at_fork(after_in_child=_forget_server)


@contextlib.contextmanager
def _subreaper() -> Iterator[None]:
    """This process the subreaper of its orphaned descendants for the block, as it was
    after it."""
    prctl = _prctl()
    was = ctypes.c_int(0)
    if prctl(PR_GET_CHILD_SUBREAPER, ctypes.byref(was), 0, 0, 0) != 0 or \
            prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "cannot receive the writer process (prctl)")
    try:
        yield
    finally:
        prctl(PR_SET_CHILD_SUBREAPER, was.value, 0, 0, 0)


def _prctl() -> Any:
    library = libc()
    if library is None:
        raise OSError(errno.ENOSYS, "no C library to call prctl through")
    return library.prctl


def _name_process(name: str) -> None:
    _prctl()(PR_SET_NAME, name.encode(), 0, 0, 0)


# -- the server -------------------------------------------------------------------------------
def serve_forks(fd: int) -> None:
    """Fork a writer for each request on socket ``fd`` until the loop process closes it."""
    from hil.core.realtime import ordinary_thread
    from hil.core.recording import writer

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    ordinary_thread()  # what a hardened loop thread that started it would have passed on
    _name_process(SERVER_NAME)

    with socket.socket(fileno=fd) as loop:
        while True:
            message, fds, _flags, _address = socket.recv_fds(loop, REQUEST_BYTES, 16)
            if not message:
                return
            try:
                request = json.loads(message)
                pid = _fork(writer.serve, request["options"], fds, request["pass_fds"])
                loop.send(str(pid).encode())
            except Exception as exc:  # the loop process says it
                loop.send(f"{type(exc).__name__}: {exc}".encode()[:64])
            finally:
                for received in fds:
                    os.close(received)


def _fork(serve: Callable[[dict[str, Any]], int], options: dict[str, Any], fds: list[int],
          pass_fds: list[int]) -> int:
    """Fork the writer through an intermediate process that ends at once: orphaned, it goes
    to the loop process, the subreaper. Its pid."""
    said_pid, tell_pid = os.pipe()
    intermediate = os.fork()
    if intermediate == 0:
        try:
            writer_pid = os.fork()
            if writer_pid == 0:
                code = 1
                try:
                    _become_writer(fds, pass_fds)
                    code = serve(options)
                finally:
                    os._exit(code)
            os.write(tell_pid, str(writer_pid).encode())
        finally:
            os._exit(0)
    os.close(tell_pid)
    with open(said_pid, "rb") as said:
        told = said.read()
    os.waitpid(intermediate, 0)
    return int(told)


def _become_writer(fds: list[int], pass_fds: list[int]) -> None:
    """In the writer: its own session, the loop process's record stream on 0, its words on
    1, standard error on 2, its working directory, ``pass_fds`` under their numbers, nothing
    else open."""
    gc.freeze()  # the server's objects: their finalizers are not the writer's to run
    os.setsid()
    _name_process(WRITER_NAME)
    stream_in, said_out, stderr, here, *passed = fds
    os.fchdir(here)
    targets = [0, 1, 2, *pass_fds]
    above = max(targets) + 1  # out of every target's way first
    moved = [fcntl.fcntl(fd, fcntl.F_DUPFD, above) for fd in (stream_in, said_out, stderr,
                                                                 *passed)]
    for fd, target in zip(moved, targets, strict=True):
        os.dup2(fd, target, inheritable=False)
    for fd in [int(name) for name in os.listdir("/proc/self/fd")]:
        if fd not in targets:
            with contextlib.suppress(OSError):  # listdir's own, closed already
                os.close(fd)


if __name__ == "__main__":
    serve_forks(int(sys.argv[1]))
