"""hil writes its manufacturer objects (0x2000-0x5FFF) to its own drive emulator only: a
vendor's drive (tests/drive_slave.py: canopen's LocalNode, identity 0xC0FFEE, with objects of
its own at 0x2003 and 0x2005) run from the command line over python-can's virtual bus is never
written one; lockstep watches it on the wall clock, and the disturbance scenario, which needs
the emulator's 0x2003, is refused in one line. hil's emulator over socketcand still keeps the
master's time."""

from __future__ import annotations

import uuid

import pytest

from hil.core.recording.reader import read_session
from hil.drivers.canopen.identity import MANUFACTURER_OBJECTS
from tests.cli import hil_here
from tests.drive_slave import serve
from tests.served_here import drive_served_here

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

NODE = 3


@pytest.fixture
def vendor_drive():
    url = f"virtual://vendor-{uuid.uuid4().hex}"
    network, slave = serve(url, NODE)
    yield url, slave
    network.disconnect()


def manufacturer_writes(slave):
    return [(hex(index), sub) for index, sub, _ in slave.writes if index in MANUFACTURER_OBJECTS]


def clock_events(path):
    return [m for _, m in read_session(path).topic("/events") if m["kind"] == "drive.clock"]


def test_lockstep_with_a_vendors_drive_writes_none_of_hils_objects(vendor_drive, tmp_path,
                                                                   capsys):
    url, slave = vendor_drive
    run = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive", url, "--node",
                   NODE, "--duration", "0.1", "--out", "vendor.mcap", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert slave.writes and manufacturer_writes(slave) == []
    assert slave.value(0x2005) == 200  # its brake release delay is its own
    clock = clock_events(tmp_path / "vendor.mcap")
    assert len(clock) == 1 and clock[0]["data"]["shared"] is False
    assert "drive node 3 is not hil's drive emulator (0x1018: vendor 0xC0FFEE, product 0x11" \
        in clock[0]["message"]
    assert "watches it on the wall clock" in clock[0]["message"]


def test_the_disturbance_scenario_is_refused_on_a_vendors_drive(vendor_drive, tmp_path,
                                                                capsys):
    url, slave = vendor_drive
    run = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive", url, "--node",
                   NODE, "--reference", "disturbance:torque=300", "--duration", "0.3",
                   "--out", "push.mcap", cwd=tmp_path)
    assert run.returncode == 2
    line = run.stderr.strip()
    assert line.count("\n") == 0 and line.startswith("hil: error: the disturbance scenario ")
    assert "0x2003" in line and "not hil's drive emulator" in line
    assert manufacturer_writes(slave) == []
    assert slave.value(0x2003) == 0


def test_hils_own_emulator_still_keeps_the_masters_time(tmp_path, capsys):
    with drive_served_here() as emulator:
        run = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive", emulator.url,
                       "--duration", "0.1", "--out", "own.mcap", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    clock = clock_events(tmp_path / "own.mcap")
    assert len(clock) == 1 and clock[0]["data"]["shared"] is True
