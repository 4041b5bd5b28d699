"""SIGINT to a running loop process: safe-state hooks run and the file is finished and indexed."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from hil.core.recording.reader import read_session

pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]

CHILD = """
import sys
from hil.core.clock import RealtimeClock
from hil.core.loop import FunctionTask, Task
from hil.core.session import Session

class Relay(Task):
    def safe_state(self):
        with open({marker!r}, "a") as f:
            f.write("relay-safe\\n")

class Driver:
    def safe_state(self):
        with open({marker!r}, "a") as f:
            f.write("driver-safe\\n")

session = Session({path!r}, RealtimeClock(), 0.001, kind="test")
topic = session.topic("/tick", {{"type": "object", "title": "Tick"}})
session.add_task(Relay("relay", 10))
def sample(t):
    if topic.log(t, {{"t": t}}):
        sample.logged += 1
        if sample.logged in (1, 300):  # the loop is ticking; 300 ticks are logged
            print("running" if sample.logged == 1 else "300 ticks", flush=True)

sample.logged = 0
session.add_task(FunctionTask("sample", 1, write=sample))
session.add_component(Driver())
session.run(duration_s=60)
session.close()
print("closed", flush=True)
"""


@pytest.mark.realtime  # a 1 kHz loop on the wall clock
def test_sigint_runs_safe_state_hooks_and_finishes_the_file(tmp_path, run_python):
    path, marker = tmp_path / "int.mcap", tmp_path / "marker.txt"
    child = run_python(CHILD.format(path=str(path), marker=str(marker)))
    try:
        assert child.stdout.readline().strip() == "running"
        assert child.stdout.readline().strip() == "300 ticks"
        child.send_signal(signal.SIGINT)
        out, err = child.communicate(timeout=30)
    finally:
        child.kill()
    assert child.returncode == 0, err
    assert "closed" in out
    assert sorted(marker.read_text().split()) == ["driver-safe", "relay-safe"]
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()  # finished: summary and index present
    assert summary is not None and summary.chunk_indexes
    data = read_session(path)
    assert not data.recovered
    assert len(data.topic("/tick")) > 200
    stop = [m for _, m in data.topic("/events") if m["kind"] == "session.stop"]
    assert stop and stop[0]["data"]["reason"] == "signal SIGINT"


# a lockstep run (no wall clock): with the rest of the suite
@pytest.mark.parametrize(("sig", "status"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signalled_run_says_so_and_exits_128_plus_the_signal(tmp_path, sig, status):
    """A lockstep run stopped by Ctrl-C (or SIGTERM) is not a completed run: its KPIs are in the
    finished session, the exit status is the shell's for a signal, one line says so."""
    out = tmp_path / "stopped.mcap"
    run = subprocess.Popen([sys.executable, "-m", "hil", "servo", "run", "--controller", "pid",
                            "--duration", "1000", "--out", str(out), "--json"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           env=dict(os.environ, PYTHONPATH=str(ROOT)))
    try:
        deadline = time.monotonic() + 30
        while (not out.exists() or out.stat().st_size < 100_000) and \
                time.monotonic() < deadline:
            time.sleep(0.1)
        run.send_signal(sig)
        stdout, stderr = run.communicate(timeout=30)
    finally:
        run.kill()
    assert run.returncode == status
    assert json.loads(stdout)["status"] == "interrupted"  # the KPIs so far, not complete
    lines = stderr.strip().splitlines()
    name = signal.Signals(sig).name
    assert len(lines) == 1 and lines[0].startswith(f"hil: interrupted by {name} after "), stderr
    data = read_session(out)
    assert not data.recovered and "kpis" in data.metadata
    assert json.loads(data.metadata["kpis"]["json"])["stop_reason"] == f"signal {name}"
