"""The drive's own settings are never lost, tried against hil's drive emulator (its 0x6072
max torque 1000 mA at power-on) over socketcand: a standalone ``hil emulate drive`` where it
falls silent or dies, elsewhere served in this process (a process start is some 0.45 s of CPU).
A run at ``--umax 300`` writes 300 to 0x6072 and puts 1000 back, also after its link is lost
(once the drive answers again at the close); when the drive is silent at the close, the journal
keeps what the run left, and the next run puts it back before it reads the drive's limits. A
limit that cuts what was asked is one terminal line."""

from __future__ import annotations

import json
import os
import signal

import pytest

from hil import api
from hil.drivers.canopen.errors import DriveGoneError, DriveLinkLostError
from hil.drivers.canopen.master import CanDriveMaster
from hil.emulator_process import EmulatorProcess
from hil.emulators.drive.timebase import TIME_BASE
from hil.protocols.cia402 import OPERATION_ENABLED, state_of
from hil.servo.rig import open_drive, share_lockstep_time
from hil.servo.run import ServoRunOptions, run_servo
from tests.cli import hil_here
from tests.served_here import drive_served_here

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

# lockstep over the bus; a drive silent for half a second is gone
PATIENCE = "[master]\nlockstep_timeout_ms = 500\n"


def max_torque(capsys, url):
    read = hil_here(capsys, "drive", "sdo", "read", url, "0x6072", "--type", "u16", "--json")
    assert read.returncode == 0, read.stderr
    return json.loads(read.stdout)["value"]


@pytest.fixture
def state(tmp_path, monkeypatch):
    """The journal's folder (HIL_STATE_DIR) of this test."""
    folder = tmp_path / "state"
    monkeypatch.setenv("HIL_STATE_DIR", str(folder))
    return folder / "drive-settings"


def journals(folder):
    return sorted(p.name for p in folder.glob("*.json")) if folder.exists() else []


def test_a_run_puts_the_drives_limit_back_also_after_its_link_was_lost(tmp_path, capsys,
                                                                        state):
    config = tmp_path / "drive.toml"
    config.write_text(PATIENCE)
    # TPDOs dropped from 0.05 s of the drive's time on (its SYNCs': 100 ticks into the run),
    # while it still answers SDO
    with drive_served_here(clock="sync", faults=["drop_tpdo@0.05"]) as drive:
        assert max_torque(capsys, drive.url) == 1000
        run = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive", drive.url,
                       "--config", config, "--umax", "300", "--duration", "1", "--out",
                       "lost.mcap", cwd=tmp_path)
        assert run.returncode == 3, run.stderr  # the drive gone quiet: a disturbed run
        assert "link lost" in run.stderr or "the drive is gone" in run.stderr
        assert max_torque(capsys, drive.url) == 1000  # on main: 300, this run's
    assert journals(state) == []


def test_a_limit_left_on_a_silent_drive_is_put_back_by_the_next_run(tmp_path, capsys, state):
    config = tmp_path / "drive.toml"
    config.write_text(PATIENCE)
    with api.start_drive_emulator() as drive:
        stopped = []

        def freeze(_master):  # configured and enabled: now the drive falls silent
            os.kill(drive.pid, signal.SIGSTOP)
            stopped.append(True)

        try:
            with pytest.raises(DriveGoneError):
                run_servo(ServoRunOptions(controller="pid", drive=drive.url, umax=300,
                                          drive_config=str(config), duration_s=10.0,
                                          out=str(tmp_path / "first.mcap")), on_started=freeze)
        finally:
            if stopped:
                os.kill(drive.pid, signal.SIGCONT)
        [journal] = journals(state)
        left = json.loads((state / journal).read_text())
        assert left["node"] == 1 and left["bus"] == drive.url
        assert left["identity"]["product_code"] == 0x402
        assert {"index": 0x6072, "subindex": 0, "fmt": "<H", "found": 1000,
                "written": 300} in left["settings"]
        assert max_torque(capsys, drive.url) == 300  # left behind
        # meanwhile someone sets the drive's heartbeat (the run wrote 100 ms): that one is
        # the drive's own now
        assert hil_here(capsys, "drive", "sdo", "write", drive.url, "0x1017", "250", "--type",
                        "u16").returncode == 0
        # the drive faulted when its master fell silent: the next run clears that and asks
        # for 800 mA, which the drive's own 1000 mA allows
        second = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive", drive.url,
                          "--config", config, "--umax", "800", "--reset-fault", "--duration",
                          "0.2", "--json", "--out", "second.mcap", cwd=tmp_path)
        assert second.returncode == 0, second.stderr
        assert json.loads(second.stdout)["current_limit_mA"] == 800  # on main: 300
        assert "hil: warning: drive node 1: put back what an earlier run (pid " in second.stderr
        assert "0x6072:00 300 -> 1000" in second.stderr
        assert "0x1017:00" in second.stderr.split("changed since, left as they are: ")[1]
        assert max_torque(capsys, drive.url) == 1000
        heartbeat = hil_here(capsys, "drive", "sdo", "read", drive.url, "0x1017", "--type",
                             "u16", "--json")
        assert json.loads(heartbeat.stdout)["value"] == 250
    assert journals(state) == []


def test_a_limit_that_cuts_what_was_asked_is_one_line(tmp_path, capsys):
    run = hil_here(capsys, "servo", "run", "--controller", "pid", "--umax", "12000",
                   "--allow-higher-current", "--duration", "0.05", "--json", "--out",
                   "cut.mcap", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout)["current_limit_mA"] == 1000
    [cut] = [line for line in run.stderr.splitlines() if "cuts it" in line]
    assert cut == ("hil: warning: drive node 1: current limit: asked 12000 mA (--umax), "
                   "applied 1000 mA: the drive's max torque (0x6072) 1000 mA cuts it")
    asked = hil_here(capsys, "servo", "run", "--controller", "pid", "--umax", "800",
                     "--duration", "0.05", "--out", "asked.mcap", cwd=tmp_path)
    assert asked.returncode == 0 and "cuts it" not in asked.stderr


def test_a_run_puts_the_drives_pdo_maps_back(tmp_path, capsys, state):
    """The PDO maps are settings too: a run with one TPDO (tpdo_layout = "one": TPDO1 remapped,
    TPDO2 invalidated) leaves the drive's power-on maps as it found them."""
    config = tmp_path / "drive.toml"
    config.write_text('[master]\ntpdo_layout = "one"\nsync_echo = ""\n')
    objects = ("0x1800:1", "0x1801:1", "0x1A00:0", "0x1A00:1", "0x1A00:2", "0x1A00:3")

    def read_all(url):
        values = {}
        for name in objects:
            done = hil_here(capsys, "drive", "sdo", "read", url, name, "--type", "u32" if
                            name.endswith((":1", ":2", ":3")) else "u8", "--json")
            assert done.returncode == 0, done.stderr
            values[name] = json.loads(done.stdout)["value"]
        return values

    with drive_served_here() as drive:
        found = read_all(drive.url)
        run = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive", drive.url,
                       "--config", config, "--duration", "0.05", "--out", "one.mcap",
                       cwd=tmp_path)
        assert run.returncode == 0, run.stderr
        assert read_all(drive.url) == found  # on main: TPDO1 three objects, TPDO2 invalid
    assert journals(state) == []


def drive_emulator_on(port: int) -> EmulatorProcess:
    """``hil emulate drive`` bound to ``port`` on loopback (a port another emulator held)."""
    return EmulatorProcess(["drive", "--socketcand", f"127.0.0.1:{port}", "--node", "1"],
                           "drive")


def driving(url: str, events: list[dict]) -> CanDriveMaster:
    """A master driving the drive at ``url`` on the master's time (0x2005), its events kept."""
    def keep(kind: str, message: str, **data: object) -> None:
        events.append({"kind": kind, "message": message, **data})

    master = open_drive(url, on_event=keep)
    assert share_lockstep_time(master, keep), events
    master.start()
    for _ in range(5):
        master.exchange(0.0)
    return master


def test_a_master_that_lost_its_drive_puts_nothing_on_the_one_now_at_its_url(state):
    """A's emulator dies while its master drives it; B's, another process, now listens on
    the same port, driven by its own master on the master's time. A's master closes: it
    reaches the URL again, finds another drive there (0x1018) and writes nothing to it (no
    disable voltage, no 0x2005 = 0 that would put B back on its wall clock): an event says
    so, and A's journal stays for A."""
    first_events: list[dict] = []
    gone = drive_emulator_on(0)
    port = int(gone.url.rsplit(":", 1)[1])
    first = driving(gone.url, first_events)
    os.kill(gone.pid, signal.SIGKILL)
    gone.stop()
    with pytest.raises(DriveLinkLostError):
        for _ in range(10_000):  # until the master finds the link lost
            first.exchange(0.0)
    other = drive_emulator_on(port)
    try:
        assert other.url == gone.url
        second_events: list[dict] = []
        second = driving(other.url, second_events)
        try:
            first.close()
            assert second.sdo.read_int(TIME_BASE, 0) == 10_000  # on main: 0, the first's restore
            assert state_of(second.exchange(0.0).statusword) == OPERATION_ENABLED  # on main: off
            [told] = [e for e in first_events if e["kind"] == "drive.not_the_drive_opened"]
            assert told["message"].startswith(
                f"drive node 1 at {gone.url} is not the drive the run opened")
            assert "nothing put back; the journal keeps it" in told["message"]
        finally:
            second.close()
    finally:
        other.stop()
    [kept] = journals(state)  # the first drive's (the second's put back and gone)
    assert json.loads((state / kept).read_text())["identity"] == first.settings.identity.as_dict()
