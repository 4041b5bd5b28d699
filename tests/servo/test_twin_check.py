"""``hil twin check`` from the command line: a recording replayed into its twin. The emulator
that made a recording is its perfect twin (fit 100 %, exit 0); a machine with friction the
twin lacks fails the fit (exit 1); what cannot be checked is one line, exit 2. The first check
runs as a ``hil`` process from a folder outside the repository, the others run the command line
in this process (:func:`hil_here`); the two recordings are made once (:func:`recorded`)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from hil.core.recording.reader import read_session
from tests.cli import hil_here, hil_in

pytestmark = [pytest.mark.slow]

FRICTION = "[emulator.friction]\ncoulomb_mA = 80.0\nviscous_mA_per_deg_s = 0.5\n"


def hil(cwd, *args):
    """``hil ARGS`` in a process of its own, from a folder outside the repository."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=180)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """0.3 s of pid on the emulator (``same.mcap``) and on a machine with friction the twin
    lacks (``machine.mcap``), recorded once, in this process."""
    folder = tmp_path_factory.mktemp("recorded")
    (folder / "machine.toml").write_text(FRICTION)
    for name, *extra in (("same.mcap",), ("machine.mcap", "--config", "machine.toml")):
        assert hil_in(folder, "servo", "run", "--controller", "pid", "--duration", "0.3",
                      "--quiet", "--out", name, *extra) == 0, name
    return folder


def record(recorded: Path, tmp_path: Path, name: str) -> Path:
    """The recording ``name`` of :func:`recorded`, in the test's own folder."""
    return Path(shutil.copy(recorded / name, tmp_path / name))


def test_the_emulator_is_its_own_perfect_twin_and_a_machine_with_friction_is_not(
        recorded, tmp_path, capsys):
    same = record(recorded, tmp_path, "same.mcap")
    machine = record(recorded, tmp_path, "machine.mcap")

    done = hil(tmp_path, "twin", "check", same.name, "--json", "--out", "same.png")
    assert done.returncode == 0, done.stderr
    check = json.loads(done.stdout)
    assert check["passed"] is True and check["min_fit_pct"] == 80.0
    assert {o["name"] for o in check["outputs"]} == {"position_deg", "velocity_deg_s"}
    for output in check["outputs"]:  # the same emulator, the same currents: the same response
        assert output["fit_pct"] == 100.0 and output["max_error"] == 0.0
        assert output["samples"] == len(read_session(str(same)).topic("/drive/feedback"))
    assert (tmp_path / "same.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    twin = read_session(str(tmp_path / check["session"]))
    assert twin.metadata["session"]["kind"] == "servo"
    assert check["session"] == "same.twin.mcap"

    done = hil_here(capsys, "twin", "check", machine.name, cwd=tmp_path)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "FAIL: every output's fit must reach 80 %" in done.stdout
    position = next(line for line in done.stdout.splitlines() if "position_deg" in line)
    assert "fit" in position and "max error" in position


def test_the_minimum_fit_decides_the_exit_status(recorded, tmp_path, capsys):
    machine = record(recorded, tmp_path, "machine.mcap")
    done = hil_here(capsys, "twin", "check", machine.name, "--json", cwd=tmp_path)
    fits = [o["fit_pct"] for o in json.loads(done.stdout)["outputs"]]
    below = min(fits) - 1.0
    done = hil_here(capsys, "twin", "check", machine.name, "--min-fit", str(below),
                    "--twin-out", "again.mcap", cwd=tmp_path)
    assert done.returncode == 0, done.stdout
    assert (tmp_path / "again.mcap").exists()


@pytest.mark.parametrize(("args", "message"), [
    (("nothing.mcap",), "nothing.mcap"),
    (("same.mcap", "--model", "absent.json"), "--model absent.json: no such file"),
    (("same.mcap", "--min-fit", "120"), "expected a fit in %, at most 100, got 120"),
    (("same.mcap", "--twin-out", "same.mcap"), "is the recording itself"),
])
def test_what_cannot_be_checked_is_one_line(recorded, tmp_path, capsys, args, message):
    record(recorded, tmp_path, "same.mcap")
    done = hil_here(capsys, "twin", "check", *args, cwd=tmp_path)
    assert done.returncode == 2, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], done.stderr
