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
from tests.cli import hil_here

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


def test_csp_tracks_the_default_reference_with_the_kpis_and_plots_of_cst(tmp_path):
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
    report = hil("report", "csp.mcap", "--out", "csp.png", "--json", cwd=tmp_path)
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


def test_csp_over_the_wire_with_a_controller_of_ones_own(tmp_path):
    """The standalone emulator, lockstep over socketcand; a user's position controller."""
    with api.start_drive_emulator() as emulator:
        kpis = api.run_servo(PositionPd, {"gain": 0.2}, drive=emulator.url, duration_s=0.3,
                             drive_overrides={"master": {"mode": "csp"}},
                             out=str(tmp_path / "own.mcap"))
    assert kpis["set_point"] == "position" and kpis["ticks"] == 600
    assert kpis["rms_error_deg"] < 0.1
