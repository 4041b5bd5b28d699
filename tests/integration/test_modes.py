"""The CiA 402 modes of the mode table from the command line, run from a folder of its own as a
user runs ``hil``: CSP (and CSV, PV) end to end in ``hil servo run`` with a controller that
returns positions (the built-in ``setpoint``), the same KPIs and plots as CST from the drive's
feedback; a current controller in a mode that takes positions refused before anything is
opened, in one line naming the mode. Each command runs from outside once; its variants run
``main`` in this process (``hil_here``)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hil import api
from hil.core.recording.reader import read_session
from hil.errors import UsageError
from tests.cli import hil_here
from tests.served_here import drive_served_here

pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]


def hil(*args, cwd):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "hil", *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def mode_config(folder, mode, name=None):
    path = folder / f"{name or mode}.toml"
    path.write_text(f'[master]\nmode = "{mode}"\n')
    return path.name


def test_csp_tracks_the_default_reference_with_the_kpis_and_plots_of_cst(tmp_path, capsys):
    csp = hil("servo", "run", "--controller", "setpoint", "--config",
              mode_config(tmp_path, "csp"), "--duration", "0.5", "--json", "--out", "csp.mcap",
              cwd=tmp_path)
    assert csp.returncode == 0, csp.stderr
    kpis = json.loads(csp.stdout)
    assert kpis["set_point"] == "position" and kpis["ticks"] == 1000
    assert kpis["stop_reason"] == "completed" and kpis["stale_feedback"] == 0
    assert kpis["rms_error_deg"] < 0.1 and kpis["max_error_pct"] < 10  # the drive follows
    assert 0 < kpis["peak_current_mA"] <= kpis["current_limit_mA"]  # the drive's current
    cst = api.run_servo("pid", duration_s=0.5, out=str(tmp_path / "cst.mcap"))
    assert set(kpis) == set(cst) | {"set_point"}
    data = read_session(str(tmp_path / "csp.mcap"))
    commands = list(data.topic("/drive/command"))
    assert len(commands) == 1000
    _, first = commands[0]
    # the set point is where the reference is one period ahead (multi-turn degrees)
    assert first["set_point_deg"] == pytest.approx(first["reference_deg"], abs=0.01)
    assert first["command_mA"] != first["command_mA"]  # NaN: the drive chooses the current
    report = hil_here(capsys, "report", "csp.mcap", "--out", "csp.png", "--json", cwd=tmp_path)
    assert report.returncode == 0, report.stderr
    assert json.loads(report.stdout)["kpis"]["rms_error_deg"] == kpis["rms_error_deg"]
    assert (tmp_path / "csp.png").stat().st_size > 10_000


@pytest.mark.parametrize("controller", ["pid", "mpc", "empc"])
def test_a_current_controller_in_csp_is_refused_before_anything_is_opened(tmp_path, capsys,
                                                                         controller):
    refused = hil_here(capsys, "servo", "run", "--controller", controller, "--config",
                       mode_config(tmp_path, "csp"), "--out", "x.mcap", cwd=tmp_path)
    assert refused.returncode == 2
    assert refused.stderr == (
        f"hil: error: controller {controller!r} returns a current [mA]: a drive in CSP (cyclic "
        "synchronous position, [master] mode = 'csp') takes a position [deg] every cycle; "
        "--controller setpoint sends the reference as one, or your own with output = "
        "'position'\n")
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "sessions").exists()


def test_a_set_point_controller_in_cst_and_a_profile_mode_are_refused(tmp_path, capsys):
    in_cst = hil_here(capsys, "servo", "run", "--controller", "setpoint", cwd=tmp_path)
    assert in_cst.returncode == 2 and in_cst.stderr.startswith(
        "hil: error: controller 'setpoint' returns a position [deg] or velocity [deg/s]: a "
        "drive in CST (cyclic synchronous torque, [master] mode = 'cst') takes a current [mA]")
    in_pp = hil_here(capsys, "servo", "run", "--controller", "setpoint", "--config",
                     mode_config(tmp_path, "pp"), cwd=tmp_path)
    assert in_pp.returncode == 2 and in_pp.stderr == (
        "hil: error: [master] mode = 'pp': hil servo run sends a set point every cycle (CST, "
        "CSP, CSV, PV); PP (profile position) runs with hil drive move\n")


def test_servo_identify_in_another_mode_is_refused(tmp_path, capsys):
    refused = hil_here(capsys, "servo", "identify", "--config", mode_config(tmp_path, "csp"),
                       "--out", "id.mcap", cwd=tmp_path)
    assert refused.returncode == 2 and refused.stderr == (
        "hil: error: hil servo identify excites the axis with currents, in CST: [master] mode "
        "= 'csp' sends the drive other set points; give it a config with mode = \"cst\"\n")


class PositionPd:
    """A controller of the user's that returns positions: the reference, nudged by the error
    (its own outer loop around the drive's)."""

    output = "position"
    position_input = "unwrapped"

    def __init__(self, reference, params):
        self.reference, self.gain = reference, params.get("gain", 0.5)

    def step(self, position_deg, t_s):
        import numpy as np

        r = float(self.reference.position(np.array([t_s + 500e-6]))[0])
        return r + self.gain * (r - position_deg)


def test_csp_over_the_wire_with_a_controller_of_ones_own(tmp_path, capsys):
    """hil's emulator lockstep over socketcand (served in this process); a user's position
    controller. The scan claims CSP (on main it did, and every CSP run failed)."""
    with drive_served_here() as emulator:
        scanned = hil_here(capsys, "drive", "scan", emulator.url, "--config",
                           mode_config(tmp_path, "csp"), cwd=tmp_path)
        kpis = api.run_servo(PositionPd, {"gain": 0.2}, drive=emulator.url, duration_s=0.3,
                             drive_overrides={"master": {"mode": "csp"}},
                             out=str(tmp_path / "own.mcap"))
    assert scanned.returncode == 0 and "can drive: yes, in CSP" in scanned.stdout
    assert kpis["set_point"] == "position" and kpis["ticks"] == 600
    assert kpis["rms_error_deg"] < 0.1


# -- PP and HM against a drive hil did not write (tests/drive_slave.py) ----------------------
NODE = 3


@pytest.fixture
def profile_drive(monkeypatch):
    """canopen's LocalNode with every mode: CSP and CSV its own loops, PP a trapezoid by
    0x6081/0x6083/0x6084 and the new-set-point handshake, PV a ramp, HM methods 35 and 37, on
    a virtual bus of its own."""
    import uuid

    import canopen

    from tests.drive_slave import CSP, CST, CSV, HM, PP, PV, dictionary, serve

    monkeypatch.setattr(canopen.Network, "NOTIFIER_CYCLE", 0.1)
    drives = []

    def start(without=()):
        url = f"virtual://modes-{uuid.uuid4().hex}"
        network, slave = serve(url, NODE, od=dictionary(
            NODE, without=without, modes=(CST, CSP, CSV, PP, PV, HM)))
        drives.append(network)
        return url, slave

    yield start
    for network in drives:
        network.disconnect()


@pytest.mark.parametrize("mode, set_point", [("csp", "position"), ("csv", "velocity"),
                                             ("pv", "velocity")])
def test_a_drive_that_closes_its_loop_follows_the_set_points_of_servo_run(
        tmp_path, capsys, profile_drive, mode, set_point):
    url, slave = profile_drive()
    (tmp_path / "mode.toml").write_text(f'[master]\nmode = "{mode}"\n[profile]\n'
                                        'acceleration_deg_s2 = 100000.0\n')
    ran = hil_here(capsys, "servo", "run", "--controller", "setpoint", "--drive", url,
                   "--node", NODE, "--config", "mode.toml", "--duration", "0.5", "--json",
                   "--out", "run.mcap", cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr
    kpis = json.loads(ran.stdout)
    assert kpis["set_point"] == set_point and kpis["rms_error_deg"] < 0.1
    # the run set the mode; the drive's own (none) is back after it
    assert slave.written(0x6060) == [{"csp": 8, "csv": 9, "pv": 3}[mode], 0]
    assert slave.value(0x6060) == 0
    commands = [m for _, m in read_session(str(tmp_path / "run.mcap")).topic("/drive/command")]
    field = "set_point_deg" if set_point == "position" else "set_point_deg_s"
    assert max(abs(m[field]) for m in commands) > 1.0  # the sine's positions or velocities


def test_a_pp_move_ends_at_its_target_and_its_profile_is_recorded(tmp_path, capsys,
                                                                  profile_drive):
    url, slave = profile_drive()
    moved = hil_here(capsys, "drive", "move", url, "90", "--node", NODE, "--velocity", "180",
                     "--acceleration", "720", "--deceleration", "720", "--json", "--out",
                     "move.mcap", cwd=tmp_path)
    assert moved.returncode == 0, moved.stderr
    kpis = json.loads(moved.stdout)
    assert kpis["motion"] == "move" and kpis["reached"] is True
    assert kpis["position_deg"] == pytest.approx(90.0, abs=0.1)  # the drive's window: 0.1 deg
    assert kpis["peak_velocity_deg_s"] == pytest.approx(180.0, rel=0.02)
    assert kpis["time_s"] == pytest.approx(0.75, abs=0.01)  # 0.25 s up, 0.25 s at 180, down
    # written in its increments, its own value put back after the move
    assert slave.written(0x6081)[0] == round(180 / 360 * (1 << 17))
    assert slave.value(0x6081) == slave.written(0x6081)[-1] != slave.written(0x6081)[0]
    data = read_session(str(tmp_path / "move.mcap"))
    assert json.loads(data.metadata["motion"]["json"])["profile velocity"] == \
        pytest.approx(180.0, rel=1e-4)
    positions = [m["position_deg"] for _, m in data.topic("/drive/feedback")]
    assert positions[0] == pytest.approx(0.0) and positions[-1] == pytest.approx(90.0, abs=0.1)
    assert len(positions) == kpis["ticks"]
    sent = [m["controlword"] for _, m in data.topic("/drive/motion")]
    assert 0x003F in sent and sent[-1] == 0x002F  # bit 4 raised once, then down
    plotted = hil_here(capsys, "report", "move.mcap", "--out", "move.png", cwd=tmp_path)
    assert plotted.returncode == 0 and (tmp_path / "move.png").stat().st_size > 10_000
    back = hil_here(capsys, "drive", "move", url, "-30", "--relative", "--node", NODE,
                    "--json", "--out", "back.mcap", cwd=tmp_path)
    assert back.returncode == 0, back.stderr
    back_kpis = json.loads(back.stdout)
    assert back_kpis["target_deg"] == pytest.approx(kpis["position_deg"] - 30.0, abs=0.01)
    assert back_kpis["position_deg"] == pytest.approx(60.0, abs=0.1)


def test_a_move_flag_wins_over_the_config_and_both_are_recorded_with_their_origin(
        tmp_path, capsys, profile_drive):
    url, slave = profile_drive()
    (tmp_path / "slow.toml").write_text("[profile]\nvelocity_deg_s = 30.0\n"
                                        "acceleration_deg_s2 = 720.0\n")
    moved = hil_here(capsys, "drive", "move", url, "10", "--node", NODE, "--config",
                     "slow.toml", "--velocity", "60", "--out", "move.mcap", cwd=tmp_path)
    assert moved.returncode == 0, moved.stderr
    settings = json.loads(read_session(str(tmp_path / "move.mcap")).metadata["config"]["json"])[
        "settings"]
    assert settings["profile.velocity_deg_s"] == {"value": 60.0, "origin": "--velocity"}
    assert settings["profile.acceleration_deg_s2"] == {"value": 720.0,
                                                       "origin": "--config slow.toml"}
    assert settings["master.mode"]["origin"] == "hil drive move"
    assert slave.written(0x6081)[0] == round(60 / 360 * (1 << 17))
    assert slave.written(0x6083)[0] == round(720 / 360 * (1 << 17))


def test_a_move_that_runs_out_of_time_and_a_value_the_drive_cannot_take_are_one_line(
        tmp_path, capsys, profile_drive):
    url, _slave = profile_drive()
    late = hil_here(capsys, "drive", "move", url, "90", "--node", NODE, "--timeout", "0.05",
                    "--out", "late.mcap", cwd=tmp_path)
    assert late.returncode == 2
    assert late.stderr.startswith("hil: error: PP move to 90 deg: not done within 0.05 s "
                                  "(statusword 0x")
    url, slave = profile_drive(without=(0x6081,))
    refused = hil_here(capsys, "drive", "move", url, "90", "--node", NODE, "--velocity", "90",
                       "--out", "refused.mcap", cwd=tmp_path)
    assert refused.returncode == 2 and refused.stderr == (
        "hil: error: drive node 3 has no 0x6081 (profile velocity): [profile] velocity_deg_s "
        "= 90 cannot take effect; leave it out to keep the drive's own\n")
    assert not (tmp_path / "refused.mcap").exists() and slave.syncs == 0


def test_home_ends_at_the_offset_with_homing_attained(tmp_path, capsys, profile_drive):
    url, _slave = profile_drive()
    none = hil_here(capsys, "drive", "home", url, "--node", NODE, "--out", "none.mcap",
                    cwd=tmp_path)
    assert none.returncode == 2 and none.stderr == (
        "hil: error: drive node 3's homing method 0x6098 is 0 (none): give --method N or "
        "[homing] method\n")
    assert not (tmp_path / "none.mcap").exists()
    homed = hil_here(capsys, "drive", "home", url, "--node", NODE, "--method", "37",
                     "--offset", "12.5", "--json", "--out", "home.mcap", cwd=tmp_path)
    assert homed.returncode == 0, homed.stderr
    kpis = json.loads(homed.stdout)
    assert kpis["reached"] is True and kpis["method"] == 37
    assert kpis["position_deg"] == pytest.approx(12.5, abs=1e-3)
    data = read_session(str(tmp_path / "home.mcap"))
    *_, (_, last) = data.topic("/drive/feedback")
    assert last["statusword"] & 0x1400 == 0x1400  # homing attained, standing
    failed = hil_here(capsys, "drive", "home", url, "--node", NODE, "--method", "17",
                      "--out", "failed.mcap", cwd=tmp_path)
    assert failed.returncode == 2 and failed.stderr.startswith(
        "hil: error: homing (method 17): the drive reports a homing error (statusword 0x")
    assert "bit 13) at 12.500 deg, standing" in failed.stderr


def test_servo_run_home_places_the_reference_absolute_from_home(tmp_path, capsys,
                                                              profile_drive):
    url, _slave = profile_drive()
    (tmp_path / "csp.toml").write_text('[master]\nmode = "csp"\n[homing]\nmethod = 35\n'
                                       'offset_deg = 100.0\n')
    ran = hil_here(capsys, "servo", "run", "--controller", "setpoint", "--drive", url,
                   "--node", NODE, "--config", "csp.toml", "--home", "--reference",
                   "hold:position=100", "--duration", "0.2", "--json", "--out", "run.mcap",
                   cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr
    assert json.loads(ran.stdout)["max_error_deg"] < 0.01  # held where home says 100 deg is
    data = read_session(str(tmp_path / "run.mcap"))
    assert data.metadata["reference"]["placed"] == "absolute (homed)"
    assert [m["kind"] for _, m in data.topic("/events")].count("drive.homed") == 1
    both = hil_here(capsys, "servo", "run", "--controller", "setpoint", "--home",
                    "--from-here", cwd=tmp_path)
    assert both.returncode == 2 and "give one" in both.stderr


def test_the_python_api_moves_and_homes(tmp_path, profile_drive):
    url, _slave = profile_drive()
    homed = api.home_drive(url, node=NODE, method=37, offset_deg=-5.0,
                           out=str(tmp_path / "h.mcap"))
    # its 17-bit encoder is single-turn: the move enables it at 355 deg, 15 deg from 340
    moved = api.move_drive(340.0, url, node=NODE, velocity_deg_s=40.0,
                           out=str(tmp_path / "m.mcap"))
    assert homed["position_deg"] == pytest.approx(-5.0, abs=0.01)  # 17-bit: 0.003 deg
    assert moved["reached"] and moved["position_deg"] == pytest.approx(340.0, abs=0.1)
    assert moved["peak_velocity_deg_s"] == pytest.approx(40.0, rel=0.02)
    with pytest.raises(UsageError, match="unknown option 'speed'"):
        api.home_drive(url, speed=3.0)


# -- every mode on hil's emulated drive ---------------------------------------------------------
def test_csv_on_the_emulator_tracks_the_default_reference(tmp_path, capsys):
    csv = hil_here(capsys, "servo", "run", "--controller", "setpoint", "--config",
                   mode_config(tmp_path, "csv"), "--duration", "0.5", "--json", "--out",
                   "csv.mcap", cwd=tmp_path)
    assert csv.returncode == 0, csv.stderr
    kpis = json.loads(csv.stdout)
    assert kpis["set_point"] == "velocity" and kpis["stale_feedback"] == 0
    assert kpis["rms_error_deg"] < 0.1 and kpis["max_error_pct"] < 10


def test_a_pp_move_on_the_emulator_ends_within_its_position_window(tmp_path):
    moved = hil("drive", "move", "emulated", "90", "--velocity", "90", "--acceleration", "360",
                "--json", "--out", "move.mcap", cwd=tmp_path)
    assert moved.returncode == 0, moved.stderr
    kpis = json.loads(moved.stdout)
    assert kpis["reached"] and abs(kpis["error_deg"]) <= 0.1  # the emulator's 0x6067
    assert kpis["peak_velocity_deg_s"] == pytest.approx(90.0, rel=0.05)
    data = read_session(str(tmp_path / "move.mcap"))
    held = json.loads(data.metadata["motion"]["json"])
    assert held["profile velocity"] == pytest.approx(90.0, rel=1e-3)
    assert held["profile acceleration"] == pytest.approx(360.0, rel=1e-3)
    *_, (_, last) = data.topic("/drive/feedback")
    assert last["statusword"] & 0x0400  # target reached


@pytest.mark.parametrize("method", [1, 2, 17, 18, 33, 34, 35, 37])
def test_every_emulated_homing_method_ends_at_home_with_bit_12(tmp_path, capsys, method):
    homed = hil_here(capsys, "drive", "home", "emulated", "--method", method, "--offset",
                     "5", "--speed", "180", "--zero-speed", "90", "--json", "--out",
                     "home.mcap", cwd=tmp_path)
    assert homed.returncode == 0, homed.stderr
    kpis = json.loads(homed.stdout)
    assert kpis["reached"] and kpis["method"] == method
    # home is the offset; the axis stops just beyond the edge or pulse it was found at
    assert kpis["position_deg"] == pytest.approx(5.0, abs=0.1)
    *_, (_, last) = read_session(str(tmp_path / "home.mcap")).topic("/drive/feedback")
    assert last["statusword"] & 0x1400 == 0x1400 and not last["statusword"] & 0x2000


def test_servo_run_home_on_the_emulator_holds_absolute_from_home(tmp_path, capsys):
    (tmp_path / "csp.toml").write_text('[master]\nmode = "csp"\n[homing]\nmethod = 17\n'
                                       'offset_deg = 0.0\nswitch_speed_deg_s = 180.0\n')
    ran = hil_here(capsys, "servo", "run", "--controller", "setpoint", "--config", "csp.toml",
                   "--home", "--reference", "hold:position=30", "--duration", "0.5", "--json",
                   "--out", "run.mcap", cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr
    data = read_session(str(tmp_path / "run.mcap"))
    assert data.metadata["reference"]["placed"] == "absolute (homed)"
    positions = data.arrays("/drive/feedback")["position_deg"]
    assert abs(positions[0]) < 0.1 and positions[-1] == pytest.approx(30.0, abs=0.5)
