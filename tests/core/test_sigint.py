"""SIGINT to a running loop process: safe-state hooks run and the file is finished and indexed."""

import signal
import time

from mcap.reader import make_reader

from hil.core.reader import read_session

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
    if topic.log(t, {{"t": t}}) and not sample.announced:
        sample.announced = print("running", flush=True) or True  # the loop is ticking

sample.announced = False
session.add_task(FunctionTask("sample", 1, write=sample))
session.add_component(Driver())
session.run(duration_s=60)
session.close()
print("closed", flush=True)
"""


def test_sigint_runs_safe_state_hooks_and_finishes_the_file(tmp_path, run_python):
    path, marker = tmp_path / "int.mcap", tmp_path / "marker.txt"
    child = run_python(CHILD.format(path=str(path), marker=str(marker)))
    try:
        assert child.stdout.readline().strip() == "running"
        time.sleep(1.0)
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
