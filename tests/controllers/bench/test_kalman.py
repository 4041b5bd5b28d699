"""Kalman filter of the bench (eq. 9 plus a disturbance state) on the emulated plant itself."""

from __future__ import annotations

import numpy as np
import pytest

from hil.bench.builtin import load_models
from hil.bench.config import load_configs
from hil.controllers.base import BenchSample
from hil.controllers.bench.kalman import BenchKalman
from hil.emulators.bench.plant import BenchPlant


def run_filter(disturbance: bool, seconds: float = 30.0):
    """Play the machining sequence and a P1/P2 schedule on the plant; filter its total VA."""
    bench, eec = load_configs(None)
    problem = bench.problem
    kalman = BenchKalman(load_models(eec, problem))
    plant = BenchPlant(bench.emulating(disturbance=disturbance).plant)
    seq = problem.sequence
    held = {name: False for name in ("M1", "M2", "P1", "P2")}
    d_hat, s_err = [], []
    for k in range(round(seconds / plant.dt)):
        if k:
            kalman.advance({m: held[m] for m in seq.relays}, {p: held[p] for p in ("P1", "P2")})
        s = plant.snapshot.meter["total_va"]
        kalman.correct(s)
        d_hat.append(kalman.disturbance_va)
        s_err.append(kalman.output_va - s)
        t = k * plant.dt
        held.update(seq.relays_at(t))
        held["P1"] = 2.0 <= t % 14.0 < 9.0
        held["P2"] = 6.0 <= t % 10.0 < 9.5
        for name, on in held.items():
            plant.set_relay(name, on)
        plant.step()
    return np.array(d_hat), np.array(s_err)


def test_models_explain_the_nominal_bench():
    d_hat, s_err = run_filter(disturbance=False)
    assert np.max(np.abs(d_hat[200:])) < 15.0       # no phantom load beyond transients
    assert np.median(np.abs(d_hat[200:])) < 3.0
    assert np.sqrt(np.mean(s_err ** 2)) < 3.0       # the filtered output follows the meter


def test_disturbance_state_finds_the_unknown_load():
    # the emulator's unknown load: 70 VA during [8, 20) s of every 56 s
    d_hat, _ = run_filter(disturbance=True)
    t = np.arange(d_hat.size) * 0.01
    assert d_hat[(t > 6.0) & (t < 8.0)].mean() == pytest.approx(0.0, abs=5.0)
    assert d_hat[(t > 10.0) & (t < 20.0)].mean() == pytest.approx(70.0, abs=5.0)
    assert d_hat[(t > 24.0) & (t < 28.0)].mean() == pytest.approx(0.0, abs=5.0)


def test_update_is_advance_then_correct_and_skips_failed_polls():
    bench, eec = load_configs(None)
    models = load_models(eec, bench.problem)
    by_hand, by_samples = BenchKalman(models), BenchKalman(models)
    readings = [40.0, 41.0, None, 300.0, 298.0]   # None: a failed poll
    relays = [{"M1": False, "P1": False}, {"M1": True, "P1": False}, {"M1": True, "P1": True},
              {"M1": True, "P1": True}, {"M1": False, "P1": True}]
    for k, (va, held) in enumerate(zip(readings, relays, strict=True)):
        if k:
            by_hand.advance(held, held)
        if va is not None:
            by_hand.correct(va)
        by_samples.update(BenchSample(k * 0.01, va, held))
    hand, samples = by_hand.estimate(), by_samples.estimate()
    assert samples.sample == hand.sample == 4
    assert np.array_equal(samples.x_machining, hand.x_machining)
    assert samples.disturbance_va == hand.disturbance_va
    assert samples.output_va == by_hand.output_va and samples.innovation_va == by_hand.innovation
