"""BC (hysteresis on the resource levels) against the resource relation of Table I."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from hil.bench.config import load_bench_config
from hil.controllers.base import BenchController, BenchObservation
from hil.controllers.bench.bc import BasicController, hysteresis_rule
from hil.controllers.bench.problem import DwellClock
from hil.controllers.errors import ControllerSetupError
from tests.cli import hil_here


def simulate_bc(cycles: int = 8, dwell_s: float = 5.0, q0: dict[str, float] | None = None,
                band: float = 1.0):
    """Closed loop of BC with eq. (10) integrated per second; returns levels and relays."""
    problem = load_bench_config().with_dwell(dwell_s).problem
    bc = BasicController(problem, band=band)
    levels = dict(q0 or {r.name: r.q0 for r in problem.resources})
    relays = {n: False for n in problem.peripherals}
    history = []
    for t in range(int(cycles * problem.sequence.period_s)):
        relays = bc.decide(BenchObservation(float(t), levels, relays, 0.0))
        history.append((t, dict(levels), dict(relays)))
        for r in problem.resources:
            used = problem.sequence.on_fraction(r.consumer, t, t + 1)
            levels[r.name] += r.alpha * used + r.eta * relays[r.supplier]
    return problem, history, levels


def test_levels_stay_in_bounds_and_relays_keep_the_dwell():
    problem, history, final = simulate_bc()
    for r in problem.resources:
        qs = [h[1][r.name] for h in history] + [final[r.name]]
        assert min(qs) >= r.q_min and max(qs) <= r.q_max
    for name in problem.peripherals:
        states = [h[2][name] for h in history]
        changes = [t for t, (a, b) in enumerate(itertools.pairwise(states)) if a != b]
        assert changes, f"{name} never switched"
        assert np.all(np.diff(changes) >= problem.dwell_s[name])


def test_switches_on_at_the_bottom_and_off_at_the_top():
    problem, history, _ = simulate_bc(cycles=8)
    for r in problem.resources:
        name = r.supplier
        for (_, q, rel), (_, _, before) in zip(history[1:], history, strict=False):
            if rel[name] and not before[name]:
                assert q[r.name] <= r.q_min + abs(r.alpha)   # on at the bottom
            if before[name] and not rel[name]:
                assert q[r.name] >= r.q_max - r.eta          # off at the top


def test_dwell_defers_a_needed_switch():
    problem = load_bench_config().with_dwell(5.0).problem
    dwell = DwellClock.start(problem.peripherals, {"P1": True, "P2": False})
    dwell.update("P1", False, 10.0)  # switched off at t = 10 s
    low = {"q1": 50.0, "q2": 150.0}
    assert hysteresis_rule(problem, low, dwell, 12.0)["P1"] is False  # inside the dwell
    assert hysteresis_rule(problem, low, dwell, 15.0)["P1"] is True   # dwell over
    dwell.update("P1", True, 15.0)
    high = {"q1": 149.0, "q2": 150.0}
    assert hysteresis_rule(problem, high, dwell, 17.0)["P1"] is True  # inside the dwell
    assert hysteresis_rule(problem, high, dwell, 20.0)["P1"] is False


def test_bc_is_a_bench_controller_that_keeps_unlisted_relays_out():
    problem = load_bench_config().problem
    bc = BasicController(problem)
    assert isinstance(bc, BenchController)
    command = bc.decide(BenchObservation(0.0, {"q1": 50.0, "q2": 150.0},
                                         {"P1": False, "P2": False}, 0.0))
    assert command == {"P1": True, "P2": False}   # q1 at its bottom: refill; q2 fine


def test_a_narrower_band_switches_off_lower_and_cycles_more_often():
    """band 0.5: off at the middle of the range instead of its top, so the levels stay in the
    lower half and the peripherals start more often over the same 8 cycles."""
    problem, full, _ = simulate_bc()
    _, half, _ = simulate_bc(band=0.5)
    for r in problem.resources:
        middle = r.q_min + 0.5 * (r.q_max - r.q_min)
        assert max(h[1][r.name] for h in half) <= middle
        assert max(h[1][r.name] for h in full) > middle
        starts = [sum(a[2][r.supplier] < b[2][r.supplier] for a, b in itertools.pairwise(run))
                  for run in (full, half)]
        assert starts[1] > starts[0]


@pytest.mark.parametrize(("param", "said"), [
    ("band=1.5", "BC's band must be in (0, 1]"),
    ("band=wide", "band must be a number in (0, 1], got 'wide'"),
    ("hysteresis=5", "controller 'bc' takes only the param band, got hysteresis")])
def test_a_wrong_bc_param_is_one_line_and_no_session(tmp_path, capsys, param, said):
    done = hil_here(capsys, "bench", "run", "--controller", "bc", "--param", param,
                    "--out", "bc.mcap", cwd=tmp_path)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1
    assert lines[0].startswith("hil: error: ") and said in lines[0]
    assert not (tmp_path / "bc.mcap").exists()


@pytest.mark.parametrize("band", [0.0, -0.5, 1.01])
def test_a_band_outside_the_range_is_refused_naming_it(band):
    with pytest.raises(ControllerSetupError, match=r"band must be in \(0, 1\]"):
        BasicController(load_bench_config().problem, band=band)
