"""Where a run's reference is placed (controllers/servo/references.py PlacedReference) and
which position a controller is given (controllers/base.py position_input_of): the turn nearest
the start by default, the start itself from here; wrapped unless a controller asks."""

import numpy as np
import pytest

from hil.controllers.base import UNWRAPPED, WRAPPED, position_input_of
from hil.controllers.errors import ControllerSetupError
from hil.controllers.servo.references import Hold, PlacedReference, Sine
from hil.errors import ConfigError


@pytest.mark.parametrize(("start", "r0", "offset"), [
    (0.0, 0.0, 0.0), (179.0, 0.0, 0.0), (264.0, 0.0, 360.0), (-200.0, 0.0, -360.0),
    (3700.0, 0.0, 3600.0), (300.0, 90.0, 360.0), (300.0, 200.0, 0.0),
])
def test_a_reference_runs_on_the_turn_nearest_the_start(start, r0, offset):
    reference = PlacedReference(Hold(r0))
    assert reference.place(start) == offset
    placed = float(reference.position(np.array([0.0]))[0])
    assert placed == r0 + offset and abs(placed - start) <= 180.0


def test_from_here_the_reference_is_a_motion_from_the_start():
    reference = PlacedReference(Sine(amplitude=2.0, frequency=1.0), relative=True)
    assert reference.place(1234.5) == 1234.5
    t = np.array([0.0, 0.25, 0.5])
    assert np.allclose(reference.position(t), 1234.5 + np.array([0.0, 2.0, 0.0]))
    assert float(reference.position(0.25)) == pytest.approx(1236.5)  # scalar time too


def test_a_reference_sampled_before_it_is_placed_says_so():
    with pytest.raises(ControllerSetupError, match=r"placed where the axis starts.*in step"):
        PlacedReference(Hold(0.0)).position(np.array([0.0]))


class Plain:
    def step(self, position_deg, t_s):
        return 0.0


class Turns(Plain):
    position_input = "unwrapped"


class Typo(Plain):
    position_input = "multi-turn"


def test_controllers_get_wrapped_positions_unless_they_ask_for_turns():
    assert position_input_of(Plain()) == WRAPPED
    assert position_input_of(Turns()) == UNWRAPPED
    with pytest.raises(ConfigError, match=r"controller 'my\.py:Typo': position_input = "
                                          r"'multi-turn': .*'wrapped'.*'unwrapped'"):
        position_input_of(Typo(), "my.py:Typo")
