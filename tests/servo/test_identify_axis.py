"""Identifying the servo axis from the command line: ``hil servo identify`` excites the
emulated drive (lockstep, deterministic) inside its current and safety limits, and ``hil
identify --servo`` finds the published axis in the session (resonance, damping, rigid-body
gain, held-out fit). Each command runs as a ``hil`` process in a folder outside the
repository; its variants (a tighter limit, a refusal, the help) run the command line in this
process (:func:`hil_here`), from the same folder."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from hil.controllers.ident.analysis import analyse
from hil.controllers.servo.model import published_axis_model
from hil.core.recording.reader import read_session
from tests.cli import hil_here

pytestmark = [pytest.mark.slow]

#: what the identified model must show (measured on 2 s, seed 1: fit 99.7 %, resonance
#: 439.87 Hz, damping 0.0113, rigid-body gain 2.831 deg/s^2 per mA)
FIT_PCT_ABOVE = 98.0
RESONANCE_HZ_WITHIN = 2.0
DAMPING_WITHIN = 0.1        # relative
RIGID_GAIN_WITHIN = 0.02    # relative


def hil(folder, *args):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run([sys.executable, "-m", "hil", *map(str, args)], cwd=folder, env=env,
                          capture_output=True, text=True, timeout=120)


def feedback(path):
    rows = [message for _, message in read_session(str(path)).topic("/drive/feedback")]
    return (np.array([row["command_mA"] for row in rows]),
            np.array([row["position_deg"] for row in rows]))


def test_the_published_axis_analysed():
    """The analysis of the printed model: one resonance near 440 Hz, two integrators, no DC
    gain but a rigid-body gain; a first-order lag has a DC gain and no integrator."""
    model = published_axis_model()
    axis = analyse(model.A, model.B, model.C, model.D, model.dt, record_s=2.0)
    assert axis.integrators == 2 and axis.dc_gain is None
    [resonance] = axis.resonances
    assert resonance.frequency_hz == pytest.approx(439.86, abs=0.01)
    assert resonance.damping_ratio == pytest.approx(0.01124, abs=1e-5)
    assert axis.integrator_gain is not None
    assert axis.integrator_gain[0, 0] == pytest.approx(2.831, abs=1e-3)
    lag = analyse(np.array([[0.9]]), np.array([[1.0]]), np.array([[1.0]]), np.zeros((1, 1)),
                  0.01, record_s=10.0)
    assert lag.integrators == 0 and lag.resonances == ()
    assert lag.dc_gain is not None and lag.dc_gain[0, 0] == pytest.approx(10.0)
    delayed = analyse(np.diag([0.0, 1.0]), np.ones((2, 1)), np.ones((1, 2)), np.zeros((1, 1)),
                      0.01, record_s=10.0)  # a pole at z = 0 (a delay) and an integrator
    assert delayed.integrators == 1 and delayed.integrator_gain is not None
    assert delayed.integrator_gain[0, 0] == pytest.approx(100.0)  # 1 per tick of 10 ms


def test_the_emulated_axis_identified_as_the_published_one(tmp_path):
    """An experiment of 2 s (safety window tightened to 5 deg), then its model: within the
    stated tolerances of the published axis."""
    session = tmp_path / "axis.mcap"
    run = hil(tmp_path, "servo", "identify", "--drive", "emulated", "--duration", "2",
              "--seed", "1", "--safety", "following_error_deg=5", "--out", session)
    assert run.returncode == 0, run.stderr
    assert f"hil identify {session} --servo" in run.stdout
    command, position = feedback(session)
    assert 300 < np.max(np.abs(command)) <= 1000        # the excitation uses its range...
    assert np.max(np.abs(position - position[0])) < 5  # ...and the axis stays near its start

    result = hil(tmp_path, "identify", session, "--servo", "--json")
    assert result.returncode == 0, result.stderr
    model = json.loads(result.stdout)
    published = analyse(*(getattr(published_axis_model(), name) for name in "ABCD"),
                        published_axis_model().dt, record_s=2.0)
    assert model["inputs"] == ["/drive/feedback:command_mA"]
    assert model["outputs"] == ["/drive/feedback:position_deg"]
    assert model["D"] == [[0.0]]
    assert model["fit_pct"] > FIT_PCT_ABOVE
    analysis = model["analysis"]
    resonance = min(analysis["resonances"],
                    key=lambda r: abs(r["frequency_hz"] - published.resonances[0].frequency_hz))
    assert resonance["frequency_hz"] == pytest.approx(published.resonances[0].frequency_hz,
                                                      abs=RESONANCE_HZ_WITHIN)
    assert resonance["damping_ratio"] == pytest.approx(published.resonances[0].damping_ratio,
                                                       rel=DAMPING_WITHIN)
    assert analysis["integrators"] == 2 and analysis["dc_gain"] is None
    assert analysis["gain_unit"] == "deg/s^2 per mA"
    assert published.integrator_gain is not None
    assert analysis["integrator_gain"][0][0] == pytest.approx(
        published.integrator_gain[0, 0], rel=RIGID_GAIN_WITHIN)
    written = json.loads((tmp_path / "axis.model.json").read_text())
    assert written["format"] == "hil.ident.state-space" and "analysis" not in written
    assert "--servo" in written["command"]


def test_a_tightened_current_limit_holds(tmp_path, capfd):
    """--umax lowers the limit; the experiment's peak (amplitude and stabiliser) stays inside
    it, with another excitation."""
    session = tmp_path / "low.mcap"
    run = hil_here(capfd, "servo", "identify", "--duration", "0.5", "--umax", "200",
                   "--amplitude", "120", "--excitation", "chirp", "--out", session, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert "|u| <= 200 mA" in run.stdout
    command, _ = feedback(session)
    assert 100 < np.max(np.abs(command)) <= 200


def test_an_amplitude_that_cannot_fit_is_one_line(tmp_path, capfd):
    run = hil_here(capfd, "servo", "identify", "--amplitude", "400", "--umax", "500",
                   "--out", tmp_path / "never.mcap", cwd=tmp_path)
    assert run.returncode == 2
    assert run.stderr.count("\n") == 1 and "Traceback" not in run.stderr
    assert "--amplitude 400 mA" in run.stderr and "current limit of 500 mA" in run.stderr
    assert "at most 333 mA" in run.stderr
    assert not (tmp_path / "never.mcap").exists()


def test_help_explains_both_commands(tmp_path, capfd):
    servo = hil_here(capfd, "servo", "identify", "--help", cwd=tmp_path)
    assert servo.returncode == 0
    text = " ".join(servo.stdout.split())
    for words in ("stabilising loop", "hil identify F.mcap --servo", "--excitation",
                  "crest factor 1", "--amplitude MA", "peak current of the excitation [mA]",
                  "--umax MA", "only lower"):
        assert words in text
    ident = hil_here(capfd, "identify", "--help", cwd=tmp_path)
    assert "--servo" in ident.stdout and "--axis NAME" in ident.stdout


def test_an_axis_of_a_session_with_several(tmp_path, capsys):
    """The experiment's controller runs on several axes as any controller does; --servo
    names the feedback topics of such a session, --axis picks one (variants of the command the
    test above runs from outside, run here)."""
    session = tmp_path / "axes.mcap"
    run = hil_here(capsys, "servo", "run", "--axes", "x=1,y=2", "--controller",
                   "hil.servo.identify:excitation", "--reference", "hold:position=0",
                   "--from-here", "--param", "y.amplitude=200", "--duration", "0.4", "--out",
                   session, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    whole = hil_here(capsys, "identify", session, "--servo", cwd=tmp_path)
    assert whole.returncode == 2
    assert "/axis/x/feedback, /axis/y/feedback (pick one with --axis NAME)" in whole.stderr
    one = hil_here(capsys, "identify", session, "--servo", "--axis", "y", "--order", "4",
                   "--block-rows", "15", "--json", cwd=tmp_path)
    assert one.returncode == 0, one.stderr
    model = json.loads(one.stdout)
    assert model["inputs"] == ["/axis/y/feedback:command_mA"]
    assert model["analysis"]["integrators"] == 2
    assert "--servo --axis y" in model["command"]


def test_servo_signals_are_not_named_twice(tmp_path, capsys):
    session = tmp_path / "never-read.mcap"  # the flags are refused before the file is read
    both = hil_here(capsys, "identify", session, "--servo", "--input", "/a:b", cwd=tmp_path)
    assert both.returncode == 2 and "leave out --input and --output" in both.stderr
    axis = hil_here(capsys, "identify", session, "--axis", "x", "--input", "/a:b",
                    "--output", "/a:c", cwd=tmp_path)
    assert axis.returncode == 2 and "--axis NAME picks an axis of a servo session" in axis.stderr


def test_print_config_says_what_the_experiment_sets(tmp_path, capsys):
    shown = hil_here(capsys, "servo", "identify", "--amplitude", "200", "--umax", "500",
                     "--print-config", "--json", cwd=tmp_path)
    assert shown.returncode == 0, shown.stderr
    settings = json.loads(shown.stdout)
    assert settings["run.controller"] == {"value": "hil.servo.identify:excitation",
                                          "origin": "hil servo identify"}
    assert settings["run.params"] == {"value": {"amplitude": 200.0}, "origin": "--amplitude"}
    assert settings["run.duration_s"] == {"value": 4.0, "origin": "hil servo identify"}
    assert settings["run.umax"] == {"value": 500.0, "origin": "--umax"}


@pytest.mark.parametrize("flags, refused", [
    (["--umax", "2000"], "--umax 2000 mA is above the configured current limit"),
    (["--safety", "following_error_deg=100"], "--safety following_error_deg 45 -> 100: looser")])
def test_a_limit_is_only_tightened(tmp_path, capsys, flags, refused):
    """The experiment has no flag to loosen a limit, and its refusal names none."""
    run = hil_here(capsys, "servo", "identify", *flags, "--out", tmp_path / "never.mcap",
                   cwd=tmp_path)
    assert run.returncode == 2 and refused in run.stderr
    assert "--allow" not in run.stderr and run.stderr.count("\n") == 1
    assert not (tmp_path / "never.mcap").exists()
