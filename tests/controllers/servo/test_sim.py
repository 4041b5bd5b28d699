"""Offline closed loop: the trends of the paper's Figs. 7-8, scenarios, the figures command."""

from __future__ import annotations

import json
from itertools import pairwise

import numpy as np
import pytest

from hil.cli.main import main
from hil.controllers.errors import ControllerSetupError
from hil.controllers.servo.model import published_axis_model
from hil.controllers.servo.mpc import MpcConfig, TrajectoryMpc
from hil.controllers.servo.pid import CascadedPid, PidConfig
from hil.controllers.servo.references import Hold, Trapezoid, parse_scenario, position_disturbance
from hil.controllers.servo.sim import cycle_error, figure_table, rest_state, simulate

MODEL = published_axis_model()


def _mpc(ert: str, ht: int, limit: float):
    cfg = MpcConfig(ht=ht, hu=ht, hp=50, ert=ert, q=1e6, r=1.0, u_min=-limit, u_max=limit)
    return lambda ref: TrajectoryMpc(ref, cfg)


@pytest.mark.parametrize(("frequency", "limit"), [(1.0, 1000.0), (10.0, 12000.0)])
def test_foh_beats_zoh_beats_setpoint_tracking_at_ht8(frequency, limit):
    errors = {name: cycle_error(_mpc(ert, ht, limit), frequency, 2.0, limit)
              for name, ert, ht in [("setpoint", "zoh", 1), ("zoh", "zoh", 8), ("foh", "foh", 8)]}
    cumulative = {name: m["cumulative_error_deg"] for name, m in errors.items()}
    assert cumulative["foh"] < cumulative["zoh"] < cumulative["setpoint"], cumulative


@pytest.mark.slow
def test_figs_7_8_trends_at_1hz_and_at_the_rated_current_for_10hz():
    table = figure_table(cases=((1.0, 1000.0), (10.0, 12000.0)))
    for case in table:
        zoh, foh = case["zoh"], case["foh"][1:]
        assert zoh[0] == pytest.approx(1.0)
        assert all(a > b for a, b in pairwise(zoh)), zoh  # error falls with H_t
        assert all(a > b for a, b in pairwise(foh)), foh
        assert all(f < z for f, z in zip(foh, zoh[1:], strict=True)), (foh, zoh)  # FOH beats ZOH
        assert all(m["peak_current_mA"] < case["current_limit_mA"]
                   for m in case["absolute"]["zoh"])  # these cases do not saturate
    ten_hz = table[1]
    assert ten_hz["foh"][-1] < ten_hz["pid"] and ten_hz["zoh"][-1] < ten_hz["pid"]


@pytest.mark.parametrize(("stroke", "top_speed"), [(270.0, 360.0), (36.0, 189.7)])
def test_trapezoid_profile_has_the_stroke_speed_and_acceleration_asked(stroke, top_speed):
    profile = Trapezoid(stroke=stroke, speed_rpm=60.0, acceleration=1000.0, offset=100.0)
    t = np.arange(0.0, profile.duration() + 0.1, 1e-4)
    p = profile.position(t)
    v = np.gradient(p, t)
    assert p[0] == 100.0 and p[-1] == pytest.approx(100.0 + stroke)
    assert p[t >= profile.duration()] == pytest.approx(100.0 + stroke)
    assert v.max() == pytest.approx(top_speed, rel=1e-3)  # 60 rpm, or triangular when short
    assert np.abs(np.diff(v) / 1e-4).max() == pytest.approx(1000.0, rel=0.01)
    assert np.all(v >= -1e-9)


def test_rest_state_stays_at_rest():
    x = rest_state(MODEL, 123.0)
    assert (MODEL.C @ x).item() == pytest.approx(123.0)
    np.testing.assert_allclose(MODEL.A @ x, x, atol=1e-9)


def test_drive_clips_what_the_controller_asks():
    pid = CascadedPid(Hold(30.0), PidConfig(u_max=5000.0))
    run = simulate(pid, Hold(30.0), 0.1, current_limit_ma=1000.0, start_deg=0.0)
    assert np.abs(run.current).max() == pytest.approx(1000.0)


def test_position_disturbance_is_rejected_after_release():
    scenario = parse_scenario("disturbance:torque=1200,start=0.1,end=0.35")
    assert scenario == position_disturbance(0.0, 1200.0, 0.1, 0.35)
    mpc = TrajectoryMpc(scenario.reference, MpcConfig(ht=3, hu=3))
    run = simulate(mpc, scenario.reference, 1.2, disturbance=scenario.disturbance)
    pushed = np.abs(run.error[run.window(0.1, 0.4)]).max()
    assert pushed > 10.0  # a torque above the 1000 mA limit displaces the axis
    assert np.abs(run.current).max() == pytest.approx(1000.0)
    assert np.abs(run.error[run.window(1.1)]).max() < 1e-3


@pytest.mark.parametrize(("spec", "match"), [
    ("circle:r=1", "unknown kind"),
    ("sine:amplitude=two", "must be a number"),
    ("sine:phase=1", "bad parameter"),
    ("sine:frequency=0", "frequency"),
    ("trapezoid:speed=-60", "speed_rpm"),
    ("disturbance:start=0.5,end=0.2", "after start"),
])
def test_bad_reference_spec_is_one_clear_error(spec, match):
    with pytest.raises(ControllerSetupError, match=match):
        parse_scenario(spec)


@pytest.mark.slow
def test_figures_command_prints_the_table_and_draws_it(tmp_path, capsys):
    png = tmp_path / "figs.png"
    assert main(["servo", "figures", "--max-ht", "2", "--json", "--out", str(png)]) == 0
    result = json.loads(capsys.readouterr().out)
    assert [(c["frequency_hz"], c["current_limit_mA"]) for c in result["cases"]] == [
        (1.0, 1000.0), (10.0, 12000.0), (10.0, 1000.0)]
    for case in result["cases"]:
        assert case["horizons"] == [1, 2] and case["zoh"][0] == pytest.approx(1.0)
        assert case["foh"][0] is None and case["foh"][1] > 0
        assert case["pid"] > 0 and case["setpoint"]["cumulative_error_deg"] > 0
    assert png.stat().st_size > 10_000 and result["png"] == str(png)


def test_figures_command_rejects_a_trajectory_horizon_beyond_hp(capsys):
    assert main(["servo", "figures", "--max-ht", "9", "--hp", "8"]) == 2
    assert capsys.readouterr().err.strip() == "hil: error: --max-ht (9) must not exceed --hp (8)"
