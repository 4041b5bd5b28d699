"""An emulator asked to listen beyond loopback says so when it starts, one line per server:
``hil emulate bench|drive`` run as a user runs them (a process, from a folder of theirs), each
on every interface, or on a loopback address other than 127.0.0.1 (no warning)."""

from __future__ import annotations

import select
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.live.test_tune_run import CONNECT_S, user_env

pytestmark = [pytest.mark.slow]

HINT = "(a 127.0.0.1 address keeps it to this machine)"


def warnings_of(cwd: Path, *args: str) -> tuple[str, list[str]]:
    """``hil emulate ARGS`` until it is ready: its ready line, and its warnings."""
    emulator = subprocess.Popen([sys.executable, "-m", "hil", "emulate", *args], cwd=cwd,
                                env=user_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
    try:
        assert emulator.stdout is not None
        deadline = time.monotonic() + CONNECT_S
        ready = ""
        while not ready and emulator.poll() is None and time.monotonic() < deadline:
            if select.select([emulator.stdout], [], [], 0.5)[0]:
                ready = emulator.stdout.readline()
    finally:
        emulator.terminate()
        _, stderr = emulator.communicate(timeout=30)
    assert ready, stderr
    return ready, [line for line in stderr.splitlines() if line.startswith("hil: warning:")]


def test_a_bench_emulator_warns_of_modbus_and_its_live_view_beyond_loopback(
        tmp_path: Path) -> None:
    ready, warnings = warnings_of(tmp_path, "bench", "--tcp", "0.0.0.0:0",
                                  "--live", "0.0.0.0:0")
    url = ready.split("listening on ", 1)[1].split()[0]
    live, modbus = warnings
    assert live.startswith("hil: warning: the live view on ws://0.0.0.0:")
    assert live.endswith(f"listens beyond loopback: any machine that reaches this one may "
                         f"watch it {HINT}")
    assert modbus == (f"hil: warning: the bench emulator on {url} listens beyond loopback: any "
                      "machine that reaches this one may read the emulated bench and switch "
                      f"its relays {HINT}")


def test_a_drive_emulator_warns_of_socketcand_beyond_loopback(tmp_path: Path) -> None:
    ready, warnings = warnings_of(tmp_path, "drive", "--socketcand", "0.0.0.0:0",
                                  "--live", "127.0.0.2:0")
    port = ready.split("on socketcand 0.0.0.0:", 1)[1].split()[0]
    assert warnings == [  # the live view on 127.0.0.2 is loopback: no warning
        f"hil: warning: the drive emulator on socketcand://0.0.0.0:{port} listens beyond "
        "loopback: any machine that reaches this one may send CAN frames to the emulated "
        f"drives {HINT}"]
