"""ExplicitMpc: a drop-in for TrajectoryMpc, with the online QP as reported fallback."""

from __future__ import annotations

import numpy as np
import pytest

from hil.controllers.servo.empc import (
    ExplicitMpc,
    build_explicit_law,
    parameter_box,
    parameter_names,
    relative_map,
)
from hil.controllers.servo.mpc import MpcConfig, TrajectoryMpc
from hil.controllers.servo.references import Modulo360, Ramp, Sine, Trapezoid, position_disturbance
from hil.controllers.servo.sim import simulate
from hil.errors import ConfigError

PAPER = MpcConfig(ht=3, hu=3, hp=50, ert="foh")


@pytest.fixture(scope="module")
def law(explicit_law):
    return explicit_law(PAPER)


@pytest.mark.parametrize(("reference", "duration"), [
    (Sine(2.0, 10.0), 0.3),  # needs more than 1000 mA: saturated, constraints active
    (Trapezoid(), 1.2),  # Fig. 14: 270 deg at 60 rpm
    (Modulo360(Ramp(720.0, 350.0)), 0.2),  # crosses 360 -> 0 repeatedly
])
@pytest.mark.slow
def test_closed_loop_equals_the_online_mpc(law, reference, duration):
    online = simulate(TrajectoryMpc(reference, PAPER), reference, duration)
    explicit_mpc = ExplicitMpc(reference, PAPER, law=law)
    explicit = simulate(explicit_mpc, reference, duration)
    np.testing.assert_allclose(explicit.current, online.current, rtol=0, atol=1e-6)
    assert explicit_mpc.fallbacks == 0 and explicit_mpc.events == []
    assert explicit_mpc.solver.counts["explicit"] == explicit.t.size


def test_saturated_run_uses_several_controllers(law):
    reference = Sine(2.0, 10.0)
    mpc = ExplicitMpc(reference, PAPER, law=law)
    used = set()
    for k in range(600):
        t = k * 5e-4
        mpc.step(float(reference.position(np.array(t))), t)
        used.add(mpc.solver.last_controller)
    assert 0 in used and len(used) >= 3


@pytest.mark.slow
def test_outside_the_box_falls_back_to_the_online_qp_and_reports_it():
    """Fig. 16 push (about 23 deg of error) with a box of |e| <= 5 deg: the ticks beyond the
    box are solved online (same currents as the online MPC), counted, and reported once on
    leaving and once on returning."""
    scenario = position_disturbance()
    small = build_explicit_law(PAPER, box="e=5")
    mpc = ExplicitMpc(scenario.reference, PAPER, law=small)
    explicit = simulate(mpc, scenario.reference, 1.2, disturbance=scenario.disturbance)
    online = simulate(TrajectoryMpc(scenario.reference, PAPER), scenario.reference, 1.2,
                      disturbance=scenario.disturbance)
    np.testing.assert_allclose(explicit.current, online.current, rtol=0, atol=1e-6)
    assert mpc.fallbacks > 100
    assert mpc.solver.counts == {"explicit": explicit.t.size - mpc.fallbacks,
                                 "fallback": mpc.fallbacks}
    events = mpc.pop_events()
    assert mpc.events == []
    kinds = [e["kind"] for e in events]
    assert kinds[0] == "empc_fallback" and kinds[-1] == "empc_resume"
    assert kinds.count("empc_fallback") == kinds.count("empc_resume")
    first = events[0]
    assert first["reason"] == "outside_box" and first["level"] == "warning"
    assert set(first["outside"]) == {"e"} and abs(first["outside"]["e"]) > 5.0
    assert 0.1 <= first["t_s"] < 0.35  # during the push
    assert sum(e["ticks"] for e in events if e["kind"] == "empc_resume") == mpc.fallbacks


def test_prediction_equals_the_online_mpc(law):
    reference = Sine(2.0, 10.0)
    online, explicit = TrajectoryMpc(reference, PAPER), ExplicitMpc(reference, PAPER, law=law)
    for k in range(120):
        t = k * 5e-4
        y = float(reference.position(np.array(t))) + 0.01 * np.sin(k)
        online.step(y, t)
        explicit.step(y, t)
    for a, b in zip(online.prediction(), explicit.prediction(), strict=True):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-6)


def test_law_for_another_config_or_with_output_limits_is_refused(law):
    with pytest.raises(ConfigError, match="another MPC config"):
        ExplicitMpc(Sine(), MpcConfig(ht=3, hu=3, hp=40), law=law)
    with pytest.raises(ConfigError, match="output limits"):
        build_explicit_law(MpcConfig(ht=3, hu=3, hp=50, y_max=10.0))


def test_relative_parameters_are_shift_invariant(law):
    """φ = Pθ drops exactly the common shift of y and the references; S inverts P."""
    P, S = relative_map(law.qp, PAPER.ht)
    np.testing.assert_allclose(P @ S, np.eye(P.shape[0]))
    shift = np.zeros(law.qp.n_theta)
    shift[law.qp.n_x - 1] = 1.0
    shift[law.qp.n_x + 1:] = 1.0
    np.testing.assert_allclose(P @ shift, 0.0)
    np.testing.assert_allclose(law.qp.F.T @ shift, 0.0, atol=1e-9 * np.abs(law.qp.F).max())


def test_box_syntax():
    names = parameter_names(4, 3)
    assert names == ["dx1", "dx2", "dx3", "dx4", "u", "e", "dr2", "dr3"]
    default = parameter_box(PAPER, 4).as_dict()
    assert default["e"] == [-180.0, 180.0] and default["u"] == [-1000.0, 1000.0]
    box = parameter_box(PAPER, 4, "e=30, dr=1, dr3=-0.5:2, dx1=-1:3, scale=2").as_dict()
    assert box["e"] == [-30.0, 30.0]
    assert box["dr2"] == [-1.0, 1.0] and box["dr3"] == [-0.5, 2.0]
    assert box["dx1"] == [-1.0, 3.0]
    assert box["dx2"] == [-6.0, 6.0]  # scaled default
    assert box["u"] == [-1000.0, 1000.0]  # never scaled
    assert parameter_box(PAPER, 4, {"u": (-500, 500)}).as_dict()["u"] == [-500.0, 500.0]
    for bad, message in [("e=0", "must be > 0"), ("e=3:1", "lo < hi"), ("x=1", "unknown"),
                         ("u=-2000:0", "current limits"), ("e", "NAME=VALUE"),
                         ("e=a", "not a number"), ("scale=-1", "scale")]:
        with pytest.raises(ConfigError, match=message):
            parameter_box(PAPER, 4, bad)
    with pytest.raises(ConfigError, match="no default for dx1"):
        parameter_box(PAPER, 3)  # another model order: the dx bounds must be given
