"""Cascaded PID + notch baseline: the notch reading, stability, anti-windup, modulo 360."""

from __future__ import annotations

import numpy as np
import pytest

from hil.controllers.servo.model import published_axis_model
from hil.controllers.servo.pid import (
    EQ16_DENOMINATOR,
    EQ16_NUMERATOR,
    CascadedPid,
    PidConfig,
    notch_coefficients,
    resonance_hz,
)
from hil.controllers.servo.references import Hold, Modulo360, Ramp, Trapezoid
from hil.controllers.servo.sim import simulate
from hil.errors import ConfigError
from hil.servo import builtin
from hil.servo.builtin import ServoContext

MODEL = published_axis_model()


def _gain(b, a, hz):
    z = np.exp(1j * 2 * np.pi * hz * MODEL.dt)
    return abs(np.polyval(b, z) / np.polyval(a, z))


def test_model_resonance_is_near_440_hz():
    assert resonance_hz(MODEL) == pytest.approx(440.0, abs=1.0)


def test_printed_notch_misses_the_resonance_and_has_dc_gain_133():
    assert _gain(EQ16_NUMERATOR, EQ16_DENOMINATOR, 0.0) == pytest.approx(1.33, abs=0.01)
    assert _gain(EQ16_NUMERATOR, EQ16_DENOMINATOR, 47.9) < 0.01  # its zero at T = 500 us
    assert _gain(EQ16_NUMERATOR, EQ16_DENOMINATOR, resonance_hz(MODEL)) > 0.9


def test_resonance_notch_has_unit_dc_gain_and_a_zero_on_the_resonance():
    b, a = notch_coefficients(resonance_hz(MODEL), PidConfig().notch_quality, MODEL.dt)
    assert _gain(b, a, 0.0) == pytest.approx(1.0, abs=1e-12)
    assert _gain(b, a, resonance_hz(MODEL)) < 1e-9
    assert np.all(np.abs(np.roots(a)) < 1.0)


@pytest.mark.parametrize("center_hz, quality, dt", [
    (None, None, None), (60.0, 30.0, 1 / 200), (1234.5, 0.7, 50e-6), (10.0, 100.0, 1e-3)])
def test_the_notch_is_scipys_iirnotch(center_hz, quality, dt):
    """Written out to spare every run scipy.signal's import; the same filter as scipy's."""
    from scipy.signal import iirnotch

    if center_hz is None:
        center_hz, quality, dt = resonance_hz(MODEL), PidConfig().notch_quality, MODEL.dt
    b, a = notch_coefficients(center_hz, quality, dt)
    want_b, want_a = iirnotch(center_hz, quality, fs=1.0 / dt)
    np.testing.assert_allclose(b, want_b, rtol=1e-14, atol=0)
    np.testing.assert_allclose(a, want_a, rtol=1e-14, atol=1e-15)


def _free_response(notch: str) -> np.ndarray:
    """|error| of the unsaturated loop released 1 deg away from its set-point."""
    pid = CascadedPid(Hold(0.0), PidConfig(notch=notch, u_max=1e12))
    run = simulate(pid, Hold(0.0), 2.0, current_limit_ma=1e12, start_deg=1.0, wrap=False)
    return np.abs(run.position)


def test_table1_gains_with_the_resonance_notch_are_stable_on_the_model():
    response = _free_response("resonance")
    assert response[-400:].max() < 1e-9  # decays from 1 deg to nothing in 2 s


def test_printed_notch_used_literally_is_unstable():
    assert _free_response("eq16")[-400:].max() > 1e3


def test_anti_windup_keeps_a_saturated_step_sane():
    run = simulate(CascadedPid(Hold(30.0)), Hold(30.0), 1.5, start_deg=0.0)
    assert np.abs(run.current).max() == pytest.approx(1000.0)  # the step saturates
    assert (run.position - 30.0).max() < 6.0  # overshoot < 20 % of the step
    assert np.abs(run.error[-200:]).max() < 1e-6


def test_command_stays_within_the_current_limit():
    pid = CascadedPid(Trapezoid(acceleration=5000.0), PidConfig(u_max=800.0))
    run = simulate(pid, Trapezoid(acceleration=5000.0), 1.0, current_limit_ma=1e9)
    assert np.abs(run.current).max() <= 800.0


def test_velocity_feedforward_removes_the_ramp_lag_of_the_p_position_loop():
    ramp = Ramp(speed_deg_s=90.0)
    lag = 90.0 / 6.0 / PidConfig().k_pos_rpm_per_deg  # v / K_pos [deg]
    plain = simulate(CascadedPid(ramp), ramp, 1.0)
    forward = simulate(CascadedPid(ramp, PidConfig(velocity_feedforward=True)), ramp, 1.0)
    assert plain.error[-1] == pytest.approx(-lag, rel=1e-3)
    assert abs(forward.error[-1]) < 0.01 * lag
    half = simulate(CascadedPid(ramp, PidConfig(velocity_feedforward=0.5)), ramp, 1.0)
    assert half.error[-1] == pytest.approx(-0.5 * lag, rel=1e-2)  # a share of it: that share


def test_the_builtin_takes_the_feedforward_share_as_a_param():
    context = ServoContext(8, 8, 50, "foh", 1000.0, None)
    assert builtin.pid(Hold(0.0), {}, context).config.velocity_feedforward == 0.0  # Table I
    assert builtin.pid(Hold(0.0), {"vff": 0.7}, context).config.velocity_feedforward == 0.7
    with pytest.raises(ConfigError, match=r"controller 'pid' params.*vff.*1"):
        builtin.pid(Hold(0.0), {"vff": 1.5}, context)


def test_reference_and_position_crossing_360_change_nothing():
    ramp = Ramp(speed_deg_s=36.0, offset=359.0)
    wrapped = simulate(CascadedPid(Modulo360(ramp)), Modulo360(ramp), 0.3, wrap=True)
    continuous = simulate(CascadedPid(ramp), ramp, 0.3, wrap=False)
    assert wrapped.position.max() > 361.0 and wrapped.reference.min() < 1.0
    np.testing.assert_allclose(wrapped.current, continuous.current, atol=1e-6)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"notch": "eq17"}, "notch"),
    ({"ti_s": 0.0}, "ti_s"),
    ({"notch_hz": 1500.0}, "notch centre"),
    ({"velocity_feedforward": -0.1}, "share in"),
])
def test_bad_configuration_is_one_clear_error(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        CascadedPid(Hold(0.0), PidConfig(**kwargs))
