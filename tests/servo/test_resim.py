"""``hil resim`` of servo sessions, from the command line: a lockstep recording re-simulated with
its own controller and parameters comes back tick for tick, its fault schedule played at the
same session time; with another gain or another axis model it differs; a recording of
hardware is re-simulated against the emulator its config describes; what cannot be
re-simulated is one line, exit 2."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from mcap.writer import Writer

from hil import api
from hil.core.recording.reader import SessionData, read_session
from tests.cli import hil_here, hil_in
from tests.served_here import drive_served_here

pytestmark = [pytest.mark.slow]  # processes, emulators, sessions

ROOT = Path(__file__).resolve().parents[2]
CONTROLLER = "my_controllers.py:PdPosition"
FAULT = "drop_tpdo@0.2-0.22:every=2"
#: what measures the computer, not the experiment
WALL_CLOCK_FIELDS = {"compute_us", "rtt_us"}
TOPICS = ("/drive/feedback", "/drive/command")


def hil(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``hil ARGS`` in a process of its own, from a folder outside the repository."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=180)


def messages(data: SessionData, topic: str) -> list[tuple[int, dict[str, Any]]]:
    """The topic's messages, each with its log time, without the wall-clock fields."""
    return [(t, {k: v for k, v in m.items() if k not in WALL_CLOCK_FIELDS})
            for t, m in data.topic(topic)]


def faults(data: SessionData) -> list[tuple[int, str]]:
    """Each fault the emulator injected, at its session time."""
    return [(t, m["data"]["fault"]) for t, m in data.topic("/events")
            if m["kind"] == "fault.injected"]


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A user's folder: their controller (a PD of the examples), a drive config with a fault
    schedule, and a 0.5 s lockstep run of it with kp = 300 (disturbed by the faults: exit 3)."""
    folder = tmp_path_factory.mktemp("resim")
    shutil.copy(ROOT / "examples" / "my_controllers.py", folder)
    (folder / "faults.toml").write_text(f'[emulator]\nfaults = ["{FAULT}"]\n')
    # in this process: each start costs a second
    assert hil_in(folder, "servo", "run", "--controller", CONTROLLER, "--param", "kp=300",
                  "--duration", "0.5", "--config", "faults.toml", "--limit",
                  "abs_error_deg<=30", "--quiet", "--out", "recorded.mcap") == 3
    return folder


def test_the_same_controller_reproduces_the_recording_tick_for_tick_with_its_faults(folder):
    done = hil(folder, "resim", "recorded.mcap", "--json")
    assert done.returncode == 3, done.stderr  # the faults disturb it as they did the recording
    kpis = json.loads(done.stdout)
    assert kpis["resim"] == {"of": "recorded.mcap", "controller": CONTROLLER,
                             "params": {"kp": 300}, "plant": "the recorded emulator",
                             "recorded_on": "emulated"}
    assert kpis["limits"][0]["limit"] == "abs_error_deg<=30"  # the recorded limits hold
    recorded, resim = read_session(folder / "recorded.mcap"), read_session(
        folder / "recorded.resim.mcap")
    for topic in TOPICS:
        mine = messages(resim, topic)
        assert len(mine) == 1000
        assert mine == messages(recorded, topic), topic
    assert faults(resim) == faults(recorded) == [(faults(recorded)[0][0], FAULT)]
    assert 0.19 < faults(resim)[0][0] / 1e9 < 0.21
    assert resim.metadata["resim"] == {
        "of": str(folder / "recorded.mcap"), "controller": CONTROLLER,
        "params": '{"kp": 300}', "plant": "the recorded emulator"}
    assert set(resim.topic_counts) == set(recorded.topic_counts)


def test_another_gain_differs_and_meets_the_same_faults(folder, capsys):
    done = hil_here(capsys, "resim", "recorded.mcap", "--param", "kp=600", "--out",
                    "kp600.mcap", cwd=folder)
    assert done.returncode == 3, done.stderr
    first = done.stdout.splitlines()[0]
    assert first == (f"resim of recorded.mcap (recorded on hil's emulator): controller "
                     f"{CONTROLLER} against the recorded emulator")
    recorded, resim = read_session(folder / "recorded.mcap"), read_session(
        folder / "kp600.mcap")
    assert json.loads(resim.metadata["resim"]["params"]) == {"kp": 600}
    position = [[m["position_deg"] for _, m in s.topic("/drive/feedback")]
                for s in (recorded, resim)]
    assert len(position[0]) == len(position[1]) and position[0] != position[1]
    assert faults(resim) == faults(recorded)
    # the log times: the same session-time grid
    assert [t for t, _ in recorded.topic("/drive/command")] == \
        [t for t, _ in resim.topic("/drive/command")]


def test_an_axis_model_file_is_the_plant(folder, capsys):
    model = ROOT / "examples" / "twin" / "machine_axis.json"
    done = hil_here(capsys, "resim", "recorded.mcap", "--model", model, "--out",
                    "model.mcap", cwd=folder)
    assert done.returncode == 3, done.stderr
    assert "against the emulator with the axis model machine_axis.json" in done.stdout
    recorded, resim = read_session(folder / "recorded.mcap"), read_session(
        folder / "model.mcap")
    assert json.loads(resim.metadata["config"]["json"])["drive"]["emulator"]["model"] == \
        str(model)
    assert messages(resim, "/drive/feedback") != messages(recorded, "/drive/feedback")
    assert len(resim.topic("/drive/feedback")) == 1000


def test_a_recording_of_hardware_is_resimulated_on_the_emulator_of_its_config(tmp_path,
                                                                               capsys):
    with drive_served_here() as drive:  # the machine: a drive over socketcand
        done = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive", drive.url,
                        "--duration", "0.1", "--quiet", "--out", "machine.mcap", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    done = hil_here(capsys, "resim", "machine.mcap", "--controller", "pid", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[0] == (
        f"resim of machine.mcap (recorded on hardware at {drive.url}): controller pid "
        "against hil's emulator built from the recorded config")
    resim = read_session(tmp_path / "machine.resim.mcap")
    assert resim.metadata["resim"]["plant"] == "hil's emulator built from the recorded config"
    assert len(resim.topic("/drive/feedback")) == len(
        read_session(tmp_path / "machine.mcap").topic("/drive/feedback")) == 200


def write_bare_mcap(path: Path) -> None:
    """An MCAP file of another program: a topic, no hil metadata."""
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        schema = writer.register_schema("x", "jsonschema", b"{}")
        channel = writer.register_channel("/x", "json", schema)
        writer.add_message(channel, 0, b"{}", 0)
        writer.finish()


@pytest.mark.parametrize(("args", "message"), [
    (("bare.mcap",), "bare.mcap: no run configuration recorded"),
    (("../recorded.mcap", "--out", "x.mcap"),
     f"'{CONTROLLER}': no such file 'my_controllers.py'"),
    (("../recorded.mcap", "--model", "a.json", "--model", "b.json"), "--model given 2 times"),
    (("../recorded.mcap", "--model", "absent.json"), "--model absent.json: no such file"),
    (("absent.mcap",), "absent.mcap: no such session file"),
])
def test_what_cannot_be_resimulated_is_one_line(folder, capsys, args, message):
    elsewhere = folder / "elsewhere"  # the recorded controller's file is not here
    elsewhere.mkdir(exist_ok=True)
    write_bare_mcap(elsewhere / "bare.mcap")
    done = hil_here(capsys, "resim", *args, cwd=elsewhere)
    assert done.returncode == 2, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], done.stderr
    assert not (elsewhere / "x.mcap").exists()


def test_several_axes_come_back_axis_by_axis(tmp_path, capsys):
    done = hil_here(capsys, "servo", "run", "--controller", "pid", "--axes", "x=1,y=2",
                    "--reference", "circle:radius=1,feed=20", "--duration", "0.1", "--quiet",
                    "--out", "axes.mcap", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    done = hil_here(capsys, "resim", "axes.mcap", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "servo run on 2 axes" in done.stdout
    recorded, resim = read_session(tmp_path / "axes.mcap"), read_session(
        tmp_path / "axes.resim.mcap")
    for topic in ("/axis/x/feedback", "/axis/y/feedback", "/axis/y/command"):
        assert messages(resim, topic) == messages(recorded, topic), topic
        assert len(messages(resim, topic)) == 200


def test_hil_emulate_drive_plays_the_configs_faults_too(tmp_path):
    (tmp_path / "drive.toml").write_text('[emulator]\nfaults = ["silent@0"]\n')
    with api.start_drive_emulator(tmp_path / "drive.toml") as drive:
        deadline = time.monotonic() + 60  # a bound on a stuck emulator, not a measurement
        while not drive.fault_events() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert drive.fault_events()[0].startswith("silent@0 injected at t=")
