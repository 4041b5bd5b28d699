"""Start and stop ``hil emulate drive`` processes on loopback for tests (bounded waits); or
serve what one serves in a thread of the test's process (:func:`drive_served_here`)."""

from __future__ import annotations

import contextlib
import os
import re
import select
import signal
import subprocess
import sys
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from hil.emulation import ServedDrives, StopFlag, serve_drives
from hil.emulators.faults import parse_fault
from hil.servo.config import load_drive_config

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


@dataclass
class DrivesHere:
    """Drives served in this process: ``url`` is where a master reaches them."""

    url: str
    served: ServedDrives
    faults_seen: list[str] = field(default_factory=list)

    def fault_events(self) -> list[str]:
        """The faults they started injecting so far (as ``EmulatorProcess.fault_events``)."""
        return list(self.faults_seen)


@contextlib.contextmanager
def drive_served_here(config: str | os.PathLike[str] | None = None, *,
                      node: int | Iterable[int] = 1, clock: str = "auto",
                      faults: Iterable[str] = ()) -> Iterator[DrivesHere]:
    """What ``hil emulate drive --config CONFIG --node N... --clock C --fault F...`` serves,
    on socketcand 127.0.0.1 and a free port, by a thread of this process until the block
    ends: for a test whose point is not the emulator's process
    (``hil.api.start_drive_emulator`` starts one: some 0.45 s of CPU)."""
    nodes = [node] if isinstance(node, int) else list(node)
    emulator = load_drive_config(config).emulator
    seen: list[str] = []
    served = serve_drives(emulator, nodes, "127.0.0.1", 0, clock=clock,
                          faults=[*emulator.faults, *map(parse_fault, faults)],
                          on_fault=seen.append)
    stop = StopFlag()
    serving = threading.Thread(target=served.serve, args=(stop,), name="drive emulator",
                               daemon=True)
    serving.start()
    try:
        host, port = served.server.address
        yield DrivesHere(f"socketcand://{host}:{port}", served, seen)
    finally:
        stop.set()
        serving.join(10)
        served.stop()
