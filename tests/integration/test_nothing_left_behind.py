"""Nothing is left running after a run is SIGKILLed: its emulator process (real time) ends
within a couple of seconds (hil.core.lifeline), its writer finishes the session file and ends
(the file is indexed and readable)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.core.recording.reader import read_session
from hil.core.recording.writer_fork import WRITER_NAME

pytestmark = [pytest.mark.timeout(90), pytest.mark.slow, pytest.mark.realtime]
ROOT = Path(__file__).resolve().parents[2]


def children_of(pid):
    """{child pid: command line, or the name a writer process goes by} of the processes
    whose parent is ``pid``."""
    found = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            cmdline = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ")
            comm = Path(f"/proc/{entry}/comm").read_text().strip()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            found[int(entry)] = comm if comm == WRITER_NAME else cmdline.decode(errors="replace")
    return found


def alive(pid):
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def size_of(path):
    """The size of the file at ``path``, 0 while there is none."""
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0


def wait_for(condition, timeout_s):
    """Whether ``condition()`` came true within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.05)
    return condition()


def wait_gone(pid, timeout_s):
    deadline = time.monotonic() + timeout_s
    while alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    return not alive(pid)


@pytest.mark.parametrize("argv", [
    ["servo", "run", "--controller", "pid", "--realtime", "--duration", "60"],
    ["bench", "run", "--controller", "bc", "--realtime", "--cycles", "2"],
])
def test_a_sigkilled_run_leaves_no_emulator_and_a_finished_file(tmp_path, argv):
    out = tmp_path / "killed.mcap"
    run = subprocess.Popen([sys.executable, "-m", "hil", *argv, "--out", str(out)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                           env=dict(os.environ, PYTHONPATH=str(ROOT)))
    try:
        deadline = time.monotonic() + 40
        helpers = {}
        while time.monotonic() < deadline:
            helpers = children_of(run.pid)
            if any("emulate" in c for c in helpers.values()) and \
                    WRITER_NAME in helpers.values():
                break
            time.sleep(0.1)
        emulator = next(p for p, c in helpers.items() if "emulate" in c)
        writer = next(p for p, c in helpers.items() if c == WRITER_NAME)
        # the run is under way: its loop started (the staging file became the session) and
        # the file grew past what the writer had when it did (the loop's records reach it)
        assert wait_for(lambda: size_of(out) > 0, 60), "the run did not start"
        started = size_of(out)
        assert wait_for(lambda: size_of(out) > started, 30), "nothing reached the file"
        run.send_signal(signal.SIGKILL)
        run.wait(10)
        assert wait_gone(emulator, 5), "the emulator outlived its run"
        assert wait_gone(writer, 10), "the writer outlived its run"
    finally:
        if run.poll() is None:
            run.kill()
    data = read_session(str(out))
    assert data.topic_counts.get("/events", 0) > 0
    assert not data.damage  # the writer finished the file: summary and index in place
