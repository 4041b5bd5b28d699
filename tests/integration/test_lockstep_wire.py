"""One clock per lockstep run, on both sides of the wire: a lockstep master over socketcand
asks hil's drive emulator for its SYNC time (0x2005), and both then go by the master's SYNCs.
The session is the one the emulator in process records; a pause of either process is no time
at all; a drive silent for longer than the documented wall-clock bound is gone (one line, exit
3); a drive that keeps its own clock is watched on the wall clock, and says so."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hil import api
from hil.cli.main import main
from hil.core.recording.reader import read_session
from hil.drivers.canopen.errors import DriveFaultError, DriveGoneError
from hil.drivers.canopen.master import CanDriveMaster
from hil.servo.run import ServoRunOptions, run_servo
from tests.cli import hil_here
from tests.served_here import drive_served_here
from tests.session_digest import kpi_digest, session_digest

pytestmark = [pytest.mark.slow]

PID = {"controller": "pid", "reference": "sine:amplitude=2,frequency=1"}
DATA_TOPICS = ("/drive/command", "/drive/feedback", "/drive/stop", "/mpc/prediction")


def same_session(a: str, b: str) -> None:
    """Every data topic bit for bit (``/events`` says how the clock was shared, and where)."""
    first, second = session_digest(a), session_digest(b)
    for topic in DATA_TOPICS:
        assert first.get(topic) == second.get(topic), topic


def same_kpis(a: dict, b: dict) -> None:
    """Every KPI but the drive's URL and the wall-clock ones."""
    first, second = kpi_digest(a), kpi_digest(b)
    first.pop("drive"), second.pop("drive")
    assert first == second


def clock_events(path: str) -> list[dict]:
    return [m for _, m in read_session(path).topic("/events") if m["kind"] == "drive.clock"]


def pause(pid: int, after_s: float, for_s: float) -> threading.Thread:
    """SIGSTOP ``pid`` after ``after_s``, SIGCONT ``for_s`` later, in a thread of its own."""
    def run() -> None:
        time.sleep(after_s)
        os.kill(pid, signal.SIGSTOP)
        time.sleep(for_s)
        os.kill(pid, signal.SIGCONT)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_a_lockstep_session_over_the_wire_is_the_one_in_process(tmp_path):
    options = {**PID, "controller": "mpc", "duration_s": 0.5}
    alone = api.run_servo(**options, out=str(tmp_path / "in-process.mcap"))
    with api.start_drive_emulator() as drive:
        wire = api.run_servo(**options, drive=drive.url, out=str(tmp_path / "wire.mcap"))
    same_session(alone["mcap"], wire["mcap"])
    same_kpis(alone, wire)
    [event] = clock_events(wire["mcap"])
    assert event["data"]["shared"] is True and event["data"]["bound_ms"] == 10_000


def test_a_paused_emulator_is_no_time_at_all(tmp_path):
    """SIGSTOP of the emulator process for 1 s mid-run: the master waits, nothing faults, and
    the session is the unpaused one's."""
    options = {**PID, "duration_s": 1.5}
    alone = api.run_servo(**options, out=str(tmp_path / "in-process.mcap"))
    with api.start_drive_emulator() as drive:
        threads = []
        paused = run_servo(ServoRunOptions(**options, drive=drive.url,
                                           out=str(tmp_path / "paused.mcap")),
                           on_started=lambda _m: threads.append(pause(drive.pid, 0.1, 1.0)))
        threads[0].join()
    assert paused.stop_reason == "completed"
    same_session(alone["mcap"], paused.session_path)
    same_kpis(alone, paused.kpis)


def hil(cwd: Path, *argv: str) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.Popen([sys.executable, "-m", "hil", *argv], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_a_master_held_up_is_no_time_at_all(tmp_path):
    """The master silent for 1 s once the drive is enabled (a debugger, a busy machine), less
    than its bound: the drive on the master's time sees no time pass; the session is the one
    of a run nobody held up."""
    options = {**PID, "duration_s": 0.5}
    alone = api.run_servo(**options, out=str(tmp_path / "in-process.mcap"))
    with api.start_drive_emulator() as drive:
        held = run_servo(ServoRunOptions(**options, drive=drive.url,
                                         out=str(tmp_path / "held.mcap")),
                         on_started=lambda _m: time.sleep(1.0))
    assert held.stop_reason == "completed"
    same_session(alone["mcap"], held.session_path)
    same_kpis(alone, held.kpis)


def test_a_drive_silent_beyond_the_bound_is_gone(tmp_path):
    """Stopped mid-run for longer than master.lockstep_timeout_ms: the run ends, the session
    finished with what it ran; the drive, still silent at the close, cannot be confirmed
    stopped: an unsafe run (exit status 4, whatever error ended it)."""
    with api.start_drive_emulator() as drive:
        stopped = []
        with pytest.raises(DriveGoneError) as gone:
            run_servo(ServoRunOptions(**PID, duration_s=10.0, drive=drive.url,
                                      drive_overrides={"master": {"lockstep_timeout_ms": 500}},
                                      out=str(tmp_path / "gone.mcap")),
                      on_started=lambda _m: (os.kill(drive.pid, signal.SIGSTOP),
                                             stopped.append(True)))
        if stopped:
            os.kill(drive.pid, signal.SIGCONT)
    error = gone.value
    assert error.exit_status == 3 and "nothing on the bus for 0.5 s of wall time" in str(error)
    assert error.result.kpis["status"] == "unsafe"
    [unsafe] = error.result.kpis["unsafe"]
    assert "its state cannot be confirmed" in unsafe and "may still move" in unsafe
    assert read_session(str(tmp_path / "gone.mcap")).topic_counts["/drive/feedback"] > 0


def test_a_drive_gone_silent_is_said_and_exit_4_from_the_command_line(tmp_path):
    """The emulator falls silent (its 'silent' fault: bus-off, 0.2 s into its time, which is
    the SYNCs' from power-on: 400 ticks into the run, after it reached the drive; a drive
    silent from the first request on is not found, exit status 2) while a lockstep run waits on
    it (for its SDO answer or its TPDOs, whichever comes first): after the bound, one line that
    its stop cannot be confirmed and one for the error; exit status 4, the run unsafe."""
    config = tmp_path / "drive.toml"
    config.write_text("[master]\nlockstep_timeout_ms = 500\n")
    with drive_served_here(faults=["silent@0.2"], clock="sync") as drive:
        run = hil(tmp_path, "servo", "run", "--controller", "pid", "--drive", drive.url,
                  "--config", str(config), "--duration", "60", "--json", "--out", "gone.mcap")
        out, err = run.communicate(timeout=120)
    assert run.returncode == 4, err
    unsafe, line = err.strip().splitlines()
    assert unsafe.startswith("hil: unsafe: drive node 1: the link was lost while driving")
    assert line.startswith("hil: error: drive node 1 ")
    assert "nothing on the bus for 0.5 s of wall time" in line or "did not answer SDO" in line
    assert json.loads(out)["status"] == "unsafe"


def test_a_master_silent_beyond_its_bound_finds_the_drive_protected(tmp_path, capsys):
    """The other way round: a lockstep master silent for longer than it told the drive (0x2005)
    leaves it on its own clock, which reacts as to a SYNC loss: a fault, EMCY 0x8130. (Seen
    twice in loaded suite runs: the run completed with no fault, the drive having let the
    master's time go while the run was set up, see the next test; failing, this one says what
    the drive was when the master spoke again and at the end.)"""
    out = tmp_path / "left.mcap"
    resumed: list[tuple[str, bool]] = []

    def silent(_master: object) -> None:  # enabled, then silent
        time.sleep(1.5)
        resumed.append((drive.nodes[0].state, drive.nodes[0].on_master_time))

    with drive_served_here() as drive:
        try:
            run_servo(ServoRunOptions(**PID, duration_s=1.0, drive=drive.url,
                                      drive_overrides={"master": {"lockstep_timeout_ms": 300}},
                                      out=str(out)),
                      on_started=silent)
            raised = "nothing"
        except DriveFaultError as exc:
            raised = str(exc)
        if "0x8130" not in raised:  # what the drive was, and what the session recorded
            pytest.fail(
                f"raised {raised}; the drive (state, on the master's time) when the master "
                f"spoke again: {resumed}, at the "
                f"end: {drive.nodes[0].state}, on the master's time: "
                f"{drive.nodes[0].on_master_time}; the events: " + "; ".join(
                    f"{t} {m['kind']}: {m['message']}"
                    for t, m in read_session(out).topic("/events")))
        assert main(["drive", "scan", drive.url, "--json"]) == 0
    [node] = json.loads(capsys.readouterr().out)["nodes"]
    assert node["state"] == "FAULT" and node["error_code"] == 0x8130


def test_a_drive_that_let_the_time_go_while_set_up_keeps_it_again_once_enabled(
        tmp_path, monkeypatch):
    """Set up on a busy machine, a master can be silent for longer than its bound before the
    drive is enabled: the drive, not driving, lets the master's time go without a fault (the
    run then went on against a drive on its own clock, unsaid: the silent-master test saw it).
    Once the drive is enabled the master finds it so, asks again and says so: the session is
    the one the emulator in process records."""
    enable = CanDriveMaster.enable

    def stalled(master: CanDriveMaster) -> None:
        time.sleep(2.5)  # the master not scheduled for 2.5 s, over its 2 s bound
        enable(master)

    options = {**PID, "duration_s": 0.25}
    alone = api.run_servo(**options, out=str(tmp_path / "in-process.mcap"))
    monkeypatch.setattr(CanDriveMaster, "enable", stalled)
    with drive_served_here() as drive:
        # a bound of 2 s: a stall of the busiest machine once the drive is enabled faults it
        wire = api.run_servo(**options, drive=drive.url, out=str(tmp_path / "stalled.mcap"),
                             drive_overrides={"master": {"lockstep_timeout_ms": 2000}})
    shared, again = clock_events(wire["mcap"])
    assert shared["data"]["shared"] is True
    assert again["level"] == "warning" and again["data"]["taken_again"] is True
    assert again["message"].startswith("drive node 1 had let the master's time go while the "
                                       "run was set up (nothing sent for over 2000 ms")
    same_session(alone["mcap"], wire["mcap"])


def test_a_drive_on_its_own_clock_is_watched_on_the_wall_clock(tmp_path):
    # the drive's wall-clock watchdogs (SYNC loss, master heartbeat) at 10 s, not 100/300 ms:
    # this test is about the clock the run says it is on, not about a busy machine's stalls
    patient = 10_000
    config = tmp_path / "drive.toml"
    config.write_text(f"[emulator]\nsync_loss_timeout_ms = {patient}\n")
    with drive_served_here(config, clock="wall") as drive:
        kpis = api.run_servo(**PID, duration_s=0.3, drive=drive.url,
                             drive_overrides={"master": {"heartbeat_timeout_ms": patient}},
                             out=str(tmp_path / "wall.mcap"))
    [event] = clock_events(kpis["mcap"])
    assert event["level"] == "warning" and event["data"]["shared"] is False
    assert "keeps its own clock" in event["message"] and kpis["ticks"] == 600


def test_an_emulator_on_sync_time_from_power_on_serves_a_lockstep_run(tmp_path):
    options = {**PID, "duration_s": 0.25}
    alone = api.run_servo(**options, out=str(tmp_path / "in-process.mcap"))
    with api.start_drive_emulator(clock="sync") as drive:
        wire = api.run_servo(**options, drive=drive.url, out=str(tmp_path / "sync.mcap"))
    same_session(alone["mcap"], wire["mcap"])
    assert clock_events(wire["mcap"])[0]["data"]["shared"] is True


def test_hil_emulate_drive_says_its_clock_and_refuses_another(tmp_path, capsys):
    # the refusal by ``main`` in this process (the parser's, before anything is served); the
    # emulator that says its clock in a process of its own, as a user starts it
    bad = hil_here(capsys, "emulate", "drive", "--socketcand", "127.0.0.1:0", "--clock", "mains",
                   cwd=tmp_path)
    assert bad.returncode == 2 and "invalid choice: 'mains'" in bad.stderr
    served = hil(tmp_path, "emulate", "drive", "--socketcand", "127.0.0.1:0", "--clock", "wall")
    try:
        assert served.stdout is not None
        assert "(bus can0, clock wall)" in served.stdout.readline()
    finally:
        served.terminate()
        served.communicate(timeout=30)
