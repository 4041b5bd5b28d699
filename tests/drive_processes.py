"""Start and stop ``hil emulate drive`` processes on loopback for tests (bounded waits)."""

from __future__ import annotations

import os
import re
import select
import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def start_drive_emulator(config: Path | None, port: int = 0, *args: str,
                         cwd: Path | None = None) -> tuple[subprocess.Popen, int]:
    """Run the drive emulator with ``config`` (None: none) and ``args`` (``--eds F``, ``--set
    INDEX:SUB=VALUE``...) on 127.0.0.1:``port``, from ``cwd``; return it and its port."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "hil", "emulate", "drive", "--socketcand",
         f"127.0.0.1:{port}", "--node", "1",
         *(["--config", str(config)] if config is not None else []), *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=cwd)
    ready, _, _ = select.select([proc.stdout], [], [], 30)
    line = proc.stdout.readline() if ready else ""
    match = re.search(r"socketcand 127\.0\.0\.1:(\d+) ", line)
    if not match:
        proc.kill()
        pytest.fail(f"emulator did not start: {line!r} {proc.stderr.read()!r}")
    return proc, int(match.group(1))


def stop_drive_emulator(proc: subprocess.Popen) -> None:
    """Stop it cleanly (resuming it first, in case a test froze it with SIGSTOP)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGCONT)
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    proc.stdout.close()
    proc.stderr.close()


def patient_watchdogs(master: str = "", safety: str = "") -> str:
    """drive.toml text for a run on a loaded machine, where only what the test injects may end
    it: every watchdog far beyond a stall of the machine - the master's stale cycles, its
    heartbeat as the drive watches it (0x1016), the drive's heartbeat as the master watches it
    (3 periods of ``drive_heartbeat_ms``), the drive's SYNC loss, and the safety net's share
    of stale cycles and following error (a drive process held up 0.45 s leaves the axis
    blind, then over 100 deg from its reference). ``master``: more ``[master]`` lines;
    ``safety``: more ``[safety]`` lines."""
    return ("[master]\nstale_cycles = 100000\nheartbeat_timeout_ms = 5000\n"
            f"drive_heartbeat_ms = 1000\n{master}[emulator]\nsync_loss_timeout_ms = 5000\n"
            f"[safety]\nstale_share_max = 1.0\nfollowing_error_deg = 3600.0\n{safety}")
