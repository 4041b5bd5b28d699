"""The servo axis plant: the published model's physics, limits, friction, disturbance, encoder."""

import math

import pytest

from hil.controllers.servo.model import published_axis_model
from hil.emulators.drive.plant import AxisPlant, Disturbance, Friction


def run(plant: AxisPlant, current_ma: float, seconds: float) -> None:
    for _ in range(round(seconds / plant.dt)):
        plant.step(current_ma)


def test_default_model_is_the_published_one_at_500_us():
    plant = AxisPlant()
    model = published_axis_model()
    assert plant.dt == pytest.approx(500e-6)
    assert (plant.model.A == model.A).all() and (plant.model.B == model.B).all()


def test_constant_current_accelerates_at_about_2_83_deg_s2_per_ma():
    plant = AxisPlant()
    run(plant, 100.0, 1.0)
    acceleration_per_ma = 2.0 * plant.position_deg / 1.0**2 / 100.0
    assert acceleration_per_ma == pytest.approx(2.83, rel=0.01)
    assert plant.velocity_deg_s == pytest.approx(283.0, rel=0.02)


def test_current_saturates_at_the_limit():
    limited = AxisPlant(current_limit_ma=500.0)
    free = AxisPlant(current_limit_ma=500.0)
    run(limited, 5000.0, 0.2)
    run(free, 500.0, 0.2)
    assert limited.applied_current_ma == 500.0
    assert limited.position_deg == pytest.approx(free.position_deg)
    limited.step(-1e9)
    assert limited.applied_current_ma == -500.0


def test_non_finite_current_applies_nothing():
    plant = AxisPlant()
    plant.step(float("nan"))
    assert plant.applied_current_ma == 0.0 and plant.position_deg == 0.0


def test_viscous_friction_slows_a_coasting_axis_and_is_off_by_default():
    coasting, braked = AxisPlant(), AxisPlant(friction=Friction(viscous_ma_per_deg_s=2.0))
    for plant in (coasting, braked):
        run(plant, 500.0, 0.2)
        run(plant, 0.0, 0.5)
    assert coasting.velocity_deg_s == pytest.approx(2.83 * 500 * 0.2, rel=0.02)
    assert 0 < braked.velocity_deg_s < 0.2 * coasting.velocity_deg_s


def test_coulomb_friction_holds_the_axis_against_a_smaller_current():
    plant = AxisPlant(friction=Friction(coulomb_ma=200.0, coulomb_smoothing_deg_s=1.0))
    run(plant, 150.0, 0.5)
    # 150 mA cannot beat 200 mA of Coulomb friction: only the smoothing's creep, 1.0*atanh(0.75)
    assert plant.velocity_deg_s == pytest.approx(math.atanh(0.75), rel=0.01)
    run(plant, 400.0, 0.5)
    assert plant.velocity_deg_s > 100.0


def test_disturbance_torque_starts_at_its_time_and_pushes_the_axis():
    plant = AxisPlant(disturbance=Disturbance(constant_ma=-300.0, start_s=0.1))
    run(plant, 0.0, 0.1)
    assert plant.position_deg == pytest.approx(0.0, abs=1e-9)
    run(plant, 0.0, 0.1)
    assert plant.velocity_deg_s == pytest.approx(-2.83 * 300 * 0.1, rel=0.05)
    plant.extra_disturbance_ma = 300.0  # run-time injection cancels it
    v = plant.velocity_deg_s
    run(plant, 0.0, 0.1)
    assert plant.velocity_deg_s == pytest.approx(v, abs=1.0)


def test_disturbance_pulse_ends_at_its_end_time():
    plant = AxisPlant(disturbance=Disturbance(constant_ma=500.0, start_s=0.05, end_s=0.15))
    run(plant, 0.0, 0.3)
    assert plant.velocity_deg_s == pytest.approx(2.83 * 500 * 0.1, rel=0.05)  # 100 ms of push
    assert plant.disturbance.current_ma(0.15) == 0.0


def test_sine_disturbance_averages_out():
    plant = AxisPlant(disturbance=Disturbance(sine_ma=400.0, sine_hz=10.0))
    run(plant, 0.0, 1.0)  # ten whole periods
    assert abs(plant.velocity_deg_s) < 2.0
    assert plant.disturbance.current_ma(0.025) == pytest.approx(400.0)


def test_encoder_reports_increments_modulo_one_revolution():
    plant = AxisPlant(increments_per_rev=1 << 20)
    run(plant, 1000.0, 0.6)  # about 510 deg: more than one turn
    assert plant.position_deg > 360.0
    expected = math.floor((plant.position_deg % 360.0) / 360.0 * (1 << 20))
    assert plant.position_increments() == expected
    assert 0 <= plant.position_increments() < 1 << 20
    backwards = AxisPlant(increments_per_rev=1000)
    run(backwards, -100.0, 0.1)
    assert backwards.position_deg < 0
    assert backwards.position_increments() == math.floor(backwards.position_deg / 0.36) % 1000
    # what a drive puts in 0x6064 and 0x606C for that axis (its count's offset 0)
    from hil.emulators.drive.node import ACTUAL_KEYS, POSITION_KEY, VELOCITY_KEY, wire_actuals

    wire = dict(zip(ACTUAL_KEYS, wire_actuals(
        backwards.position_deg, backwards.velocity_deg_s, 1000, 0, (0.0, 0.0), 0, 0.0, 1000, 0),
        strict=True))
    assert wire[POSITION_KEY] == backwards.position_increments()
    assert wire[VELOCITY_KEY] == round(backwards.velocity_deg_s / 0.36)


@pytest.mark.parametrize("kwargs", [{"current_limit_ma": 0.0}, {"increments_per_rev": 1},
                                    {"increments_per_rev": 2**31}])
def test_invalid_parameters_are_refused(kwargs):
    with pytest.raises(ValueError):
        AxisPlant(**kwargs)


def test_a_step_is_the_product_of_the_step_matrix_bit_for_bit():
    """The plant multiplies by ``ndarray.dot`` (no ufunc's cost): the very product of
    ``np.matmul``, to the last bit, over a run with every kind of input."""
    import numpy as np

    plant = AxisPlant(friction=Friction(viscous_ma_per_deg_s=2.0))
    axis = plant.axis
    M = np.block([[axis.A, axis.B], [axis.C, axis.D]]).astype(float)
    xu, position = np.zeros(axis.n_states + 1), axis.y_offset
    for k in range(2000):
        current = 3000.0 * math.sin(k / 37.0) + (50_000.0 if k % 500 == 7 else 0.0)
        applied = min(max(current, -plant.current_limit_ma), plant.current_limit_ma)
        xu[-1] = applied - plant.load_current_ma() - axis.u_offset
        plant.step(current)
        z = np.matmul(M, xu)
        xu = z.copy()
        position = float(z[-1]) + axis.y_offset
        assert plant.position_deg == position
