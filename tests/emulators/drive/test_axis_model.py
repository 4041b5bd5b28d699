"""The drive emulator's axis from a model file: the file's equations as `hil identify --servo`
writes them (offsets applied, no feedthrough), the checks of a model that cannot be the axis,
and the period it must step in."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hil.controllers.ident.model_file import loads_model, model_file_of
from hil.controllers.servo.model import published_axis_model, resampled
from hil.emulators.drive.axis_model import (
    AxisModel,
    axis_model_file,
    load_axis_model,
    period_problem,
)
from hil.emulators.drive.plant import AxisPlant
from hil.emulators.errors import EmulatorSetupError


def test_a_model_file_runs_with_its_offsets(tmp_path):
    """The file's y(k) is the position at the start of the period u(k) is held over: after k
    cycles the plant is where the identified model's own simulation puts y(k)."""
    path = tmp_path / "offsets.json"
    path.write_text(model_file_of(published_axis_model(), ["/drive/feedback:command_mA"],
                                  ["/drive/feedback:position_deg"], u_offset=[25.0],
                                  y_offset=[30.0]))
    plant = AxisPlant(load_axis_model(str(path)))
    assert plant.position_deg == 30.0  # at rest: the output's offset
    currents = np.random.default_rng(3).uniform(-500.0, 500.0, 400)
    positions = []
    for current in currents:
        plant.step(float(current))
        positions.append(plant.position_deg)
    expected = loads_model(path.read_text()).simulate(currents[:, None])[:, 0]
    assert np.max(np.abs(np.asarray(positions[:-1]) - expected[1:])) \
        < 1e-9 * np.max(np.abs(expected))
    assert plant.applied_current_ma == currents[-1]


def test_a_model_with_feedthrough_is_refused_naming_the_servo_identification(tmp_path):
    axis = published_axis_model()
    path = tmp_path / "paired.json"
    path.write_text(model_file_of(replace(axis, D=np.array([[2e-4]])),
                                  ["/drive/feedback:command_mA"],
                                  ["/drive/feedback:position_deg"]))
    with pytest.raises(EmulatorSetupError) as refused:
        load_axis_model(str(path))
    assert str(refused.value) == (
        f"{path}: its feedthrough D is 0.0002, not 0: an axis model pairs each position with "
        "the current held after it (a current cannot move the position it starts from); "
        "identify the axis with 'hil identify F.mcap --servo'")


RUNS_AWAY = "its position leaves +-1e+12 deg within 2000 periods of 100 A"


@pytest.mark.parametrize(("what", "value", "says"), [
    # found by the fuzz campaign (tests/fuzz): A[1][0] = -2.47e17 loaded, and the drive's
    # position went infinite on the first SYNCs (floor(inf): internal errors, EMCY 0x6100)
    ("A", -2.4747881765574195e17,
     "its state matrix A grows 3.97978e+08 times per period (at most 1.001"),
    ("B", 1e308, RUNS_AWAY),
    ("C A", 1e308, "its state matrix A grows"),  # its overflow is no RuntimeWarning either
    # found by the fuzz campaign too: offsets of 1e308 (infinite increments, velocities)
    ("u_offset", 1e308, RUNS_AWAY),
    ("y_offset", 1e308, RUNS_AWAY),
])
@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_a_model_that_runs_away_is_refused(tmp_path, what, value, says):
    axis = published_axis_model()
    A, B, offsets = axis.A.copy(), axis.B.copy(), {}
    if what == "A":
        A[1, 0] = value
    elif what == "C A":  # the row the output reads
        A[2, 0] = value
    elif what == "B":
        B[0, 0] = value
    else:
        offsets[what] = [value]
    path = tmp_path / "runaway.json"
    path.write_text(model_file_of(replace(axis, A=A, B=B), ["/drive/feedback:command_mA"],
                                  ["/drive/feedback:position_deg"], **offsets))
    with pytest.raises(EmulatorSetupError) as refused:
        load_axis_model(str(path))
    assert str(refused.value).startswith(f"{path}: {says}")


def test_the_published_axis_file_is_the_default_plant():
    file_axis = AxisPlant(AxisModel.of_state_space(published_axis_model()))
    default = AxisPlant()
    for current in (300.0, -200.0, 1000.0, 0.0):
        file_axis.step(current, 3)
        default.step(current, 3)
        assert file_axis.position_deg == default.position_deg


@pytest.mark.parametrize("model_us, cycle_us, fits", [
    (500, 500, True), (250, 500, True), (500, 1500, True), (1000, 500, False),
    (300, 500, False)])
def test_the_period_divides_the_cycle_whole(model_us, cycle_us, fits):
    model = AxisModel.of_state_space(resampled(published_axis_model(), 500e-6)) \
        if model_us == 500 else AxisModel(np.eye(1), np.ones((1, 1)), np.ones((1, 1)),
                                           np.zeros((1, 1)), model_us * 1e-6)
    problem = period_problem(model, cycle_us * 1e-6)
    assert (problem is None) == fits
    if not fits:
        assert problem == (f"its period is {model_us} us: the drive's cycle of {cycle_us} us "
                           "must be a whole multiple of it")


def test_a_model_of_another_signal_is_refused_naming_it(tmp_path):
    axis = loads_model(axis_model_file(published_axis_model()))
    path = tmp_path / "speed.json"
    path.write_text(model_file_of(axis, ["/drive/feedback:command_mA"],
                                  ["/drive/feedback:velocity_deg_s"]))
    with pytest.raises(EmulatorSetupError) as refused:
        load_axis_model(str(path))
    assert str(refused.value) == (
        f"{path}: its output '/drive/feedback:velocity_deg_s' is not a position in deg (its "
        "field must end in _deg, e.g. /drive/feedback:position_deg)")
