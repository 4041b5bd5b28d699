"""Relative where the run is relative, tried as a user would against a drive on socketcand (what
``hil emulate drive`` serves, served in the test's process) whose axis stays where each run
leaves it: two runs from where the axis stands
(``--from-here``) repeat one 90 deg move from two places, and ``hil compare`` and the
``hil_baseline`` fixture (run against the drive with ``--hil-drive``) hold their positions
relative to each run's start; the drive guide's first cautious run holds an axis standing 180 deg
away instead of driving it at zero. The two runs from here and the cautious run share one drive
(:func:`moved_twice`)."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import textwrap

import pytest

from tests.cli import NOT_A_USERS_PLUGINS, hil_here, hil_in
from tests.docs import block
from tests.served_here import drive_served_here

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

MOVE = ["--controller", "pid", "--from-here", "--reference",
        "trapezoid:stroke=90,speed=180", "--duration", "1", "--quiet"]
POSITION = "/drive/feedback:position_deg"
# the second run starts with what is left of the first one's stop (the axis coasting at under
# 2 deg/s, the standstill): its currents differ by a few mA, its positions by an encoder count
CLOSE = ["--tolerance", "*=rel:5%", "--tolerance", f"{POSITION}=abs:0.01",
         "--tolerance", "/drive/command:reference_deg=abs:1e-9"]


@pytest.fixture(scope="module")
def moved_twice(tmp_path_factory):
    """A drive emulator on socketcand and a folder with two runs of :data:`MOVE` on it, one
    after the other (``first.mcap``, ``second.mcap``): its axis stands 180 deg on."""
    folder = tmp_path_factory.mktemp("from_start")
    with drive_served_here() as drive:
        for name in ("first", "second"):
            assert hil_in(folder, "servo", "run", *MOVE, "--drive", drive.url, "--out",
                          f"{name}.mcap") == 0, name
        yield drive, folder


def test_hil_compare_holds_two_runs_from_here_relative_to_their_starts(moved_twice, capsys):
    _, tmp_path = moved_twice
    compared = hil_here(capsys, "compare", "first.mcap", "second.mcap", "--signal", POSITION,
                        "--signal", "/drive/command:reference_deg", *CLOSE, "--json",
                        cwd=tmp_path)
    assert compared.returncode == 0, compared.stdout + compared.stderr  # on main: 1, by 90 deg
    document = json.loads(compared.stdout)
    rows = {row["name"]: row for row in document["rows"]}
    first_start, second_start = rows[POSITION]["from_start_deg"]
    assert first_start == pytest.approx(0.0, abs=1e-6)
    assert second_start == pytest.approx(90.0, abs=1.0)  # where the first run left the axis
    assert rows[POSITION]["passed"] and rows["max_error_deg"]["from_start_deg"] is None
    [note] = [n for n in document["notes"] if "relative to each run's start" in n]
    assert note.startswith("drive positions relative to each run's start: both started where "
                           "the axis stood (--from-here), the baseline at 0 deg, the candidate "
                           "at 8")
    table = hil_here(capsys, "compare", "first.mcap", "second.mcap", "--signal", POSITION,
                     *CLOSE, cwd=tmp_path)
    assert re.search(rf"signal {re.escape(POSITION)} \(from start\) +0 ", table.stdout)


# the test's runs are lockstep over the wire; the second's currents differ from the first's
# by up to about 70 mA while the axis accelerates (it starts coasting from the first's stop)
USER_TEST = textwrap.dedent("""
    def test_moves_as_before(hil_drive, hil_baseline):
        hil_drive.run("pid", reference="trapezoid:stroke=90,speed=180", duration_s=1.0,
                      realtime=False)
        hil_baseline.check(tolerances={"*": "rel:5%", "/drive/feedback:position_deg": "abs:0.01",
                                       "/drive/command:command_mA": "abs:150"})
""")


def test_hil_baseline_against_a_given_drive_holds_wherever_the_axis_stood(tmp_path):
    """The hardware workflow: record a baseline against the drive, run the same test again
    from where the first run left the axis (90 deg on): it holds."""
    (tmp_path / "test_mine.py").write_text(USER_TEST)
    env = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}

    def pytest_run(url: str, name: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
             *NOT_A_USERS_PLUGINS, "-n", "0",
             "--basetemp", str(tmp_path / name), "test_mine.py", "--hil-drive", url],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=200, check=False)

    with drive_served_here() as drive:
        recorded = pytest_run(drive.url, "first")
        assert recorded.returncode == 0, recorded.stdout[-3000:]
        assert "BaselineRecorded" in recorded.stdout
        again = pytest_run(drive.url, "again")
    assert again.returncode == 0, again.stdout[-3000:]  # on main: failed by 90 deg
    report = json.loads(next((tmp_path / "again").rglob("*.compare.json")).read_text())
    position = next(row for row in report["rows"] if row["name"] == POSITION)
    assert position["from_start_deg"][1] == pytest.approx(90.0, abs=1.0)


def test_the_first_cautious_run_holds_the_axis_where_it_stands(moved_twice, tmp_path, capsys):
    """The drive guide's recipe, in lockstep and for half a second (its `--realtime` and two
    seconds are for the hardware), against a drive whose axis the runs before left 180 deg
    from zero."""
    recipe = block("guides/drive.md", "sh", "--can-log first.asc").replace("\\\n", " ")
    [line] = [line for line in recipe.splitlines() if line.startswith("hil servo run")]
    argv = shlex.split(line)[1:]
    assert "--from-here" in argv
    drive, _ = moved_twice
    argv = [drive.url if arg == "socketcan://can0" else arg for arg in argv
            if arg != "--realtime"]
    argv[argv.index("--duration") + 1] = "0.5"
    cautious = hil_here(capsys, *argv, "--out", "cautious.mcap", cwd=tmp_path)
    assert cautious.returncode == 0, cautious.stderr  # on main: 2, stopped 10 ms in
    assert (tmp_path / "first.asc").stat().st_size > 0
