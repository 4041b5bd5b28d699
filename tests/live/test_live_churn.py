"""A real-time servo run with live-view clients coming and going completes; what the drive
emulator's process was granted and who was late when feedback was stale are in its session
and in `hil report`, consistent with its KPIs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from websockets.exceptions import ConnectionClosed, WebSocketException

from hil.core.recording.reader import read_session
from tests.cli import hil_here
from tests.live.foxglove_client import FoxgloveClient

pytestmark = [pytest.mark.slow, pytest.mark.realtime]

REPO = Path(__file__).resolve().parents[2]
CLIENTS = 10  # benchmarks/live.py --churn 30 measures the full churn
STEPS = ["sched_fifo", "cpu_affinity", "mlockall", "gc_freeze", "timer_slack"]


def free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def hil(cwd: Path, *args: str, **kwargs: object) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", "hil", *args], cwd=cwd, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kwargs)


def come_and_go(url: str, until: threading.Event, done: list[int]) -> None:
    """Connect, subscribe to every topic, read a little, disconnect; again until ``until``."""
    while not until.is_set():
        try:
            client = FoxgloveClient(url, timeout_s=2,  # no retries once the run is over
                                    alive=lambda: 0 if until.is_set() else None)
        except (OSError, WebSocketException):
            # not serving yet, or no more, or the server closed it during the handshake (the
            # session ending): a little later
            until.wait(0.05)
            continue
        try:
            client.wait_for(lambda c=client: bool(c.topics()) or until.is_set(), 1)
            if client.topics():
                client.subscribe(sorted(client.topics()))
                client.wait_for(lambda c=client: bool(c.messages) or until.is_set(), 0.3)
                done.append(1)
        except ConnectionClosed:
            continue  # the session ended under this client
        finally:
            client.close()


def test_a_run_with_clients_coming_and_going_completes_and_reports_who_was_late(tmp_path,
                                                                                capsys):
    port = free_port()
    run = hil(tmp_path, "servo", "run", "--controller", "pid", "--realtime", "--duration",
              "1", "--live", str(port), "--out", "churn.mcap", "--json")
    over, done = threading.Event(), []
    clients = [threading.Thread(target=come_and_go, args=(f"ws://127.0.0.1:{port}", over,
                                                          done), daemon=True)
               for _ in range(CLIENTS)]
    for client in clients:
        client.start()
    try:
        stdout, stderr = run.communicate(timeout=180)
    finally:
        over.set()
        if run.poll() is None:
            run.kill()
    for client in clients:
        client.join(timeout=60)
    # completed: 0, or 3 when some feedback was stale (the KPIs say so)
    assert run.returncode in (0, 3), stderr
    kpis = json.loads(stdout)
    assert kpis["stop_reason"] == "completed"
    assert done, "no client got through a connection"
    session = read_session(tmp_path / "churn.mcap")
    sent = json.loads(session.metadata["live"]["sent"])
    assert sum(sent.values()) > 0  # the clients were served while they came and went

    # the run is a process of its own (the clients' threads are no part of its loop); the
    # reports are read in this one
    report = json.loads(hil_here(capsys, "report", "churn.mcap", "--json", cwd=tmp_path).stdout)
    emulator = report["realtime_helpers"]["emulator"]
    assert emulator == session.metadata["realtime.emulator"]
    assert list(emulator) == ["pid", *STEPS]
    assert all(emulator[step].startswith(("granted: ", "refused: ")) for step in STEPS)
    started = next(m for _, m in session.topic("/events") if m["kind"] == "emulator.process")
    assert str(started["data"]["pid"]) == emulator["pid"]

    feedback = report["feedback"]["/drive/feedback"]
    dropped = report["dropped"]
    if not dropped:  # every tick recorded: the section counts what the KPIs counted
        assert feedback["cycles"] == kpis["ticks"]
        assert feedback["stale"] == kpis["stale_feedback"]
    assert feedback["stale_share"] == round(feedback["stale"] / feedback["cycles"], 6)
    assert (feedback["late_side"] == "none") == (feedback["stale"] == 0)
    assert feedback["late_side"] in ("none", "drive", "loop")
    assert feedback["late_frames"] == kpis["faults"]["late_frames"]
    worst = feedback["worst_window"]
    assert worst["cycles"] == min(400, feedback["cycles"]) and worst["stale"] <= feedback["stale"]
    text = hil_here(capsys, "report", "churn.mcap", cwd=tmp_path).stdout
    assert f"real-time hardening of the emulator (process {emulator['pid']})" in text
    assert f"feedback /drive/feedback: {feedback['stale']} of {feedback['cycles']} cycles " \
           f"stale" in text
