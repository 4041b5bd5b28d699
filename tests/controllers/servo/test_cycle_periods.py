"""Cycle periods other than 500 us: the axis model stepped N times (what the emulated drive
does between two SYNCs), the PID discretised at T and refused where its loop is unstable, the
MPC rebuilt at T, the explicit MPC at 500 us only, and how a controller says its periods."""

from __future__ import annotations

import numpy as np
import pytest

from hil.controllers.base import (
    CyclePeriods,
    check_cycle_period,
    cycle_periods_of,
    describe_periods,
    runs_at,
)
from hil.controllers.servo.model import axis_model, published_axis_model
from hil.controllers.servo.pid import CascadedPid, PidConfig, check_stable, closed_loop_pole
from hil.controllers.servo.references import Sine
from hil.controllers.servo.sim import simulate
from hil.emulators.drive.plant import AxisPlant
from hil.errors import ConfigError
from hil.servo import builtin
from hil.servo.builtin import ServoContext


def test_the_model_at_1_ms_is_the_emulated_axis_over_two_of_its_steps():
    model = axis_model(1e-3)
    assert model.dt == 1e-3
    assert np.array_equal(axis_model(500e-6).A, published_axis_model().A)
    plant = AxisPlant()  # the emulated drive's axis: 500 us steps, the current held per SYNC
    x = np.zeros(model.n_states)
    for current in (800.0, -300.0, 0.0, 1000.0, 250.0):
        plant.step(current, periods=2)
        x = model.A @ x + model.B[:, 0] * current
        assert float(model.C[0] @ x) == pytest.approx(plant.position_deg, rel=1e-9, abs=1e-12)
    with pytest.raises(ValueError, match="750 us is no whole multiple of the model's 500 us"):
        axis_model(750e-6)


def test_the_pids_closed_loop_pole_decides_whether_it_tracks():
    reference = Sine(2.0, 1.0)
    table_i, patient = PidConfig(u_max=1e12), PidConfig(u_max=1e12, ti_s=8e-3)
    assert closed_loop_pole(PidConfig(), axis_model()) == pytest.approx(0.989, abs=1e-3)
    model = axis_model(1e-3)
    assert closed_loop_pole(table_i, model) > 1.0 > closed_loop_pole(patient, model)
    # the same verdict from a simulation with the current unlimited
    runaway = simulate(CascadedPid(reference, table_i, model), reference, 1.0, model=model,
                       current_limit_ma=1e12)
    holds = simulate(CascadedPid(reference, patient, model), reference, 1.0, model=model,
                     current_limit_ma=1e12)
    assert runaway.metrics(0.5)["max_error_deg"] > 10.0
    assert holds.metrics(0.5)["max_error_deg"] < 1.0


def test_an_unstable_pid_is_refused_naming_an_integral_time_that_holds_it():
    check_stable(PidConfig(), axis_model())  # Table I at 500 us: stable
    with pytest.raises(ConfigError, match=r"pid: at a cycle period of 1000 us the loop is "
                       r"unstable .* \|z\| = 1\.060\) with T_i = 2000 us; a longer integral "
                       r"time holds it, e.g. --param ti_us=8000 \(\|z\| = 0\.979\)"):
        check_stable(PidConfig(), axis_model(1e-3))
    with pytest.raises(ConfigError, match="no longer integral time holds it"):
        check_stable(PidConfig(), axis_model(5e-3))


def context(period_s):
    return ServoContext(8, 8, 50, "foh", 1000.0, None, period_s)


def test_the_built_ins_are_built_at_the_runs_period():
    reference = Sine(2.0, 1.0)
    pid = builtin.pid(reference, {"ti_us": 8000}, context(1e-3))
    assert pid.dt == 1e-3 and pid.config.ti_s == pytest.approx(8e-3)
    mpc = builtin.mpc(reference, {}, context(1e-3))
    assert mpc.dt == 1e-3 and np.array_equal(mpc.model.A, axis_model(1e-3).A)
    with pytest.raises(ConfigError, match="unstable"):
        builtin.pid(reference, {}, context(1e-3))
    assert 1000 in cycle_periods_of(builtin.pid) and 1000 in cycle_periods_of(builtin.mpc)
    assert 10_500 not in cycle_periods_of(builtin.mpc)
    with pytest.raises(ConfigError, match=r"controller 'empc' does not run at a cycle period "
                       r"of 1000 us .*: it runs at 500 us"):
        check_cycle_period(builtin.empc, "empc", 1000)


class Quiet:
    def __init__(self, reference, params):
        pass

    def step(self, position_deg, t_s):
        return 0.0


class Slow(Quiet):
    cycle_periods_us = range(500, 5001, 500)


def test_a_controller_says_its_periods_or_runs_at_500_us_only():
    check_cycle_period(Quiet, "mine.py:Quiet", 500)
    with pytest.raises(ConfigError, match=r"controller 'mine\.py:Quiet' does not say it runs "
                       r"at a cycle period of 1000 us .* without cycle_periods_us runs at 500 "
                       r"us"):
        check_cycle_period(Quiet, "mine.py:Quiet", 1000)
    assert isinstance(Slow, CyclePeriods)
    check_cycle_period(Slow, "mine.py:Slow", 1500)
    with pytest.raises(ConfigError, match="it runs at multiples of 500 us up to 5000 us"):
        check_cycle_period(Slow, "mine.py:Slow", 750)

    @runs_at((1000, 2000))
    def factory(reference, params):
        return Quiet(reference, params)

    assert cycle_periods_of(factory) == (1000, 2000)
    assert describe_periods((2000, 1000)) == "1000 us, 2000 us"
    assert describe_periods(range(1000, 3001, 1000)) == "multiples of 1000 us up to 3000 us"
