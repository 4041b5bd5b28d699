"""A run that never ran leaves the disk as it was: whichever step refused it (a controller that
cannot be built, a drive that refuses its settings, a SIGKILL before the first tick), no file is
left, ``mcap`` is null, and a session already at ``--out`` survives; a device or a FIFO given as
``--out`` is refused and left alone. A run that starts replaces the earlier session, and only
then. Run from the command line in a folder of the test's own; root-safe: the only special
files a run is given to remove are ones the test made (a FIFO), and /dev/null only to a run
that is refused before anything opens."""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.core.recording.output import OutputError, claim_output
from hil.core.recording.reader import read_session
from tests.cli import hil_here

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]
ROOT = Path(__file__).resolve().parents[2]

BAD_CONTROLLER = """
class Bad:
    def __init__(self, reference, params):
        raise RuntimeError("cannot be built")

    def step(self, position_deg, t_s):
        return 0.0
"""

SLOW_CONTROLLER = """
import time


class Slow:
    def __init__(self, reference, params):
        print("building", flush=True)
        time.sleep(60)

    def step(self, position_deg, t_s):
        return 0.0
"""

EARLIER = b"an earlier session, kept by the user\n"


def listing(folder: Path) -> dict[str, bytes]:
    """Every file of ``folder`` (hidden ones included) and its bytes."""
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def one_error_line(done: subprocess.CompletedProcess[str]) -> str:
    lines = done.stderr.strip().splitlines()
    assert "Traceback" not in done.stderr
    return lines[-1]


def test_a_fifo_or_device_as_out_is_refused_and_left_alone(tmp_path, capfd):
    (tmp_path / "bad.py").write_text(BAD_CONTROLLER)
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    done = hil_here(capfd, "servo", "run", "--controller", "bad.py:Bad", "--out", fifo,
                    "--json", cwd=tmp_path)
    assert done.returncode == 2
    assert one_error_line(done) == (
        f"hil: error: session file {fifo} is a FIFO: a session is a file of its own, written "
        "then finished with its index; give a file path")
    assert json.loads(done.stdout)["mcap"] is None
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    # (Python may leave __pycache__ beside bad.py when it imports it: that is not hil's doing)
    left = sorted(p.name for p in tmp_path.iterdir() if p.name != "__pycache__")
    assert left == ["bad.py", "pipe"]

    done = hil_here(capfd, "servo", "run", "--controller", "pid", "--duration", "0.1",
                    "--out", "/dev/null", cwd=tmp_path)
    assert done.returncode == 2
    assert "session file /dev/null is a character device" in one_error_line(done)
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


@pytest.mark.parametrize("split", [[], ["--split-duration", "0.05"]], ids=["file", "series"])
def test_a_controller_that_cannot_be_built_leaves_the_earlier_session(tmp_path, capfd, split):
    (tmp_path / "bad.py").write_text(BAD_CONTROLLER)
    (tmp_path / "run.mcap").write_bytes(EARLIER)
    (tmp_path / "run_000.mcap").write_bytes(EARLIER)
    before = listing(tmp_path)
    done = hil_here(capfd, "servo", "run", "--controller", "bad.py:Bad", "--out", "run.mcap",
                    "--json", *split, cwd=tmp_path)
    assert done.returncode == 2
    assert "building it failed: RuntimeError: cannot be built" in one_error_line(done)
    assert json.loads(done.stdout)["mcap"] is None
    assert listing(tmp_path) == before  # the session as it was, no staging file left


def test_a_drive_that_refuses_its_settings_leaves_no_file_and_mcap_null(tmp_path, capfd):
    """The drive refuses the master's write of 0x6060 (read-only in its EDS): the run stops
    before its first tick. It used to leave a file and name it."""
    assert hil_here(capfd, "emulate", "drive", "--write-eds", tmp_path / "drive.eds",
                    cwd=tmp_path).returncode == 0
    eds = (tmp_path / "drive.eds").read_text()
    head, _, rest = eds.partition("[6060]\n")
    entry, _, tail = rest.partition("\n\n")
    assert "AccessType=rw" in entry
    (tmp_path / "drive.eds").write_text(
        head + "[6060]\n" + entry.replace("AccessType=rw", "AccessType=ro") + "\n\n" + tail)
    (tmp_path / "drive.toml").write_text('[emulator]\neds = "drive.eds"\n')
    (tmp_path / "run.mcap").write_bytes(EARLIER)
    before = listing(tmp_path)
    done = hil_here(capfd, "servo", "run", "--controller", "pid", "--config", "drive.toml",
                    "--duration", "0.2", "--out", "run.mcap", "--json", cwd=tmp_path)
    assert done.returncode == 2
    line = one_error_line(done)
    assert "refused SDO write 0x6060:00" in line and "session recorded" not in line
    result = json.loads(done.stdout)
    assert result["mcap"] is None and result["ticks"] == 0 and result["status"] == "failed"
    assert listing(tmp_path) == before


def test_a_run_killed_before_its_first_tick_leaves_the_earlier_session(tmp_path):
    """SIGKILL while the controller is being built: the loop process is gone at once; its
    writer process, which outlives it, removes the staging file it was writing."""
    (tmp_path / "slow.py").write_text(SLOW_CONTROLLER)
    (tmp_path / "run.mcap").write_bytes(EARLIER)
    before = listing(tmp_path)
    run = subprocess.Popen([sys.executable, "-m", "hil", "servo", "run", "--controller",
                            "slow.py:Slow", "--out", "run.mcap"], cwd=tmp_path,
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                           env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert run.stdout is not None and run.stdout.readline() == "building\n"
        assert (tmp_path / ".run.mcap.starting").exists()  # the session is being written
        run.send_signal(signal.SIGKILL)
        run.wait(timeout=30)
    finally:
        if run.poll() is None:
            run.kill()
    deadline = time.monotonic() + 30
    while listing(tmp_path) != before and time.monotonic() < deadline:
        time.sleep(0.05)
    assert listing(tmp_path) == before


def test_a_run_that_starts_replaces_the_earlier_session(tmp_path, capfd):
    (tmp_path / "run.mcap").write_bytes(EARLIER)
    done = hil_here(capfd, "servo", "run", "--controller", "pid", "--duration", "0.1",
                    "--out", "run.mcap", "--json", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["mcap"] == "run.mcap"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]
    data = read_session(tmp_path / "run.mcap")
    assert not data.recovered and data.topic_counts["/drive/command"] == 200


def test_the_claim_refuses_a_second_run_and_what_is_not_hils(tmp_path):
    out = str(tmp_path / "s.mcap")
    first = claim_output(out)
    try:
        with pytest.raises(OutputError, match="is being written by another run"):
            claim_output(out)  # still staging: nothing at the path yet
        first.start()
        with pytest.raises(OutputError, match="is being written by another run"):
            claim_output(out)  # started: the file at the path is the first run's
    finally:
        first.release()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.mcap"]
    # a staging file that is not hil's is in the way, and stays
    (tmp_path / ".t.mcap.starting").write_bytes(b"somebody's notes")
    with pytest.raises(OutputError, match=r"\.t\.mcap\.starting is in the way and is not a "
                                          "session hil began: move it away"):
        claim_output(str(tmp_path / "t.mcap"))
    assert (tmp_path / ".t.mcap.starting").read_bytes() == b"somebody's notes"
    assert not (tmp_path / "t.mcap").exists()
