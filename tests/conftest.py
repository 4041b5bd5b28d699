"""Shared fixtures."""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]

# the journals of settings runs write to drives (hil.drivers.canopen.run_settings) go to this
# test session's own folder, not the user's state folder; hil processes the tests start inherit it
if "HIL_STATE_DIR" not in os.environ:
    os.environ["HIL_STATE_DIR"] = tempfile.mkdtemp(prefix="hil-test-state-")
    atexit.register(shutil.rmtree, os.environ["HIL_STATE_DIR"], True)

# BLAS on one thread, in this process (numpy is loaded already, by hil's pytest plugin) and in
# the processes the tests start: the suite's workers fill both cores, and OpenBLAS's second
# thread only spins against them (tests/controllers/ident/test_n4sid.py: 31 s -> 3 s of CPU
# under load); the golden session digests are the same either way
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
threadpool_limits(limits=int(os.environ["OPENBLAS_NUM_THREADS"]), user_api="blas")


@pytest.fixture
def run_python():
    """Start ``python -c CODE`` in a child process with the repo importable."""

    def start(code: str, **kwargs) -> subprocess.Popen:
        env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
        return subprocess.Popen(
            [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, env=env, **kwargs,
        )

    return start


@pytest.fixture
def socketcand_server():
    """A socketcand server on 127.0.0.1 (any free port) that keeps the frames it receives in
    ``.received``."""
    from hil.emulators.socketcand_server import SocketcandServer

    frames: list = []
    server = SocketcandServer("127.0.0.1", 0, on_frame=frames.append).start()
    server.received = frames
    yield server
    server.close()


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Ray's tests first: Ray takes 10-25 s to start, and a worker that starts it late keeps the
    other one waiting at the end of the suite (the not-realtime tests: 218 s in the order of the
    files, 191 s with Ray's first, 209 s with every slow test first as well)."""
    items.sort(key=lambda item: "local_ray" not in getattr(item, "fixturenames", ()))


def _scheduling() -> tuple[list[tuple[int, int]], set[int]]:
    """Each thread of this process' (id, policy), and the process' CPUs."""
    threads = []
    for tid in map(int, os.listdir("/proc/self/task")):
        with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
            threads.append((tid, os.sched_getscheduler(tid)))
    return threads, os.sched_getaffinity(0)


@pytest.fixture(autouse=True)
def ordinary_test_process():
    """A test leaves its pytest process as it found it: no thread left real-time (SCHED_FIFO)
    or pinned to a CPU by a run or emulator served in process, which every process the worker
    starts after it would inherit (a busy-machine test's spinning processes, SCHED_FIFO on the
    emulators' CPU, starved every emulator there for minutes). It is put back, and the test
    that left it so fails."""
    cpus = os.sched_getaffinity(0)
    yield
    threads, now = _scheduling()
    changed = [tid for tid, policy in threads if policy != os.SCHED_OTHER]
    for tid in changed:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
    if now != cpus:
        os.sched_setaffinity(0, cpus)
    assert not changed and now == cpus, (
        f"the test left threads {changed} real-time or the process on CPUs {sorted(now)} "
        f"(was {sorted(cpus)})")
