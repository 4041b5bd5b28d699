"""Kalman filter of the bench (eq. 9 plus a disturbance state) on the emulated plant itself."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.bench_kalman import BenchKalman
from emulators.bench_plant import BenchPlant
from hil.bench.config import load_configs
from hil.bench.run import load_models


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
