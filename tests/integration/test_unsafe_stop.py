"""A safe stop that fails is an outcome of its own, tried from outside: a lockstep run against
what ``hil emulate drive`` serves (in the test's process), on SYNC time, whose link is cut
during the stop (the emulator falls silent 40 ms into the quick stop of an axis turning at
200 deg/s), and the emulated drive ignoring the controlword. The terminal says what the drive
last reported and that the axis may still move; ``--json``, ``--junit``, ``hil report`` and its
HTML page say ``unsafe``; the exit status is 4."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import pytest

from tests.cli import hil_here
from tests.served_here import drive_served_here

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

# the run ends at 0.3 s of drive time with the axis at about 200 deg/s; its quick stop takes
# about 85 ms: the drive falls silent in the middle of it
MOVING = ["--reference", "trapezoid:stroke=3600,speed=300", "--duration", "0.3"]


def test_a_link_lost_during_the_stop_is_unsafe_exit_4(tmp_path, capsys):
    config = tmp_path / "drive.toml"
    config.write_text("[master]\nlockstep_timeout_ms = 500\n")
    with drive_served_here(clock="sync", faults=["silent@0.34"]) as drive:
        run = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive", drive.url,
                       "--config", config, *MOVING, "--json", "--junit", "run.xml",
                       "--out", "cut.mcap", cwd=tmp_path)
    assert run.returncode == 4, run.stderr
    kpis = json.loads(run.stdout)
    assert kpis["status"] == "unsafe" and kpis["stop_reason"] == "completed"
    [line] = kpis["unsafe"]
    assert line.startswith("drive node 1: safe stop incomplete (drive node 1 link lost: ")
    assert "; it last reported QUICK STOP ACTIVE (statusword 0x" in line
    assert line.endswith(": the axis may still move")
    assert f"hil: unsafe: {line}" in run.stderr.splitlines()
    root = ET.parse(tmp_path / "run.xml").getroot()
    [case] = [c for c in root.iter("testcase") if c.get("name") == "run"]
    error = case.find("error")
    assert error is not None and error.get("type") == "UnsafeStop"
    report = hil_here(capsys, "report", "cut.mcap", "--html", "cut.html", cwd=tmp_path)
    assert report.returncode == 0, report.stderr
    assert f"UNSAFE: {line}" in report.stdout.splitlines()
    page = (tmp_path / "cut.html").read_text()
    assert "FAILED (unsafe)" in page and "UNSAFE: drive node 1: safe stop incomplete" in page
    summary = json.loads(hil_here(capsys, "report", "cut.mcap", "--json",
                                  cwd=tmp_path).stdout)
    assert summary["unsafe"] == [line] and summary["kpis"]["status"] == "unsafe"


def test_a_drive_that_ignores_the_stop_is_unsafe(tmp_path, capsys):
    config = tmp_path / "drive.toml"
    # the emulated drive ignores every controlword from 0.1 s of its time on; its SYNC watchdog
    # is what is left to fault it
    config.write_text('[emulator]\nfaults = ["ignore_controlword@0.1"]\n')
    run = hil_here(capsys, "servo", "run", "--controller", "pid", "--config", config,
                   "--duration", "0.2", "--out", "ignored.mcap", cwd=tmp_path)
    assert run.returncode == 4, run.stderr  # on main: 0, "completed"
    [line] = [line for line in run.stderr.splitlines() if line.startswith("hil: unsafe: ")]
    assert "drive node 1 ignored quick stop and disable voltage: it last reported OPERATION " \
        "ENABLED" in line and line.endswith("the axis may still move")
