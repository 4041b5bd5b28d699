"""Shared fixtures."""

from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# the journals of settings runs write to drives (hil.drivers.canopen.run_settings) go to this
# test session's own folder, not the user's state folder; hil processes the tests start inherit it
if "HIL_STATE_DIR" not in os.environ:
    os.environ["HIL_STATE_DIR"] = tempfile.mkdtemp(prefix="hil-test-state-")
    atexit.register(shutil.rmtree, os.environ["HIL_STATE_DIR"], True)


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
