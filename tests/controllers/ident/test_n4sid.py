"""N4SID on systems whose truth is known: exact recovery, fit with noise, order selection,
noise model, bad input, model files."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from hil.controllers.ident import n4sid as ident
from hil.controllers.ident.model_file import (
    MODEL_FORMAT,
    dumps_model,
    loads_model,
    model_to_dict,
)
from hil.controllers.ident.n4sid import IdentificationError


def random_stable_system(rng: np.random.Generator, n: int, m: int, ny: int):
    """Random (A, B, C, D) with spectral radius drawn in [0.5, 0.95]."""
    A = rng.normal(size=(n, n))
    A *= rng.uniform(0.5, 0.95) / np.max(np.abs(np.linalg.eigvals(A)))
    return A, rng.normal(size=(n, m)), rng.normal(size=(ny, n)), rng.normal(size=(ny, m))


def bench_like_plant():
    """A motor's apparent power [VA] after its relay closes: inrush peak, then ~1000 VA.

    Modes at 0.01 s sampling: 20 ms, 50 ms and 300 ms time constants.
    """
    poles = np.exp(-0.01 / np.array([0.02, 0.05, 0.3]))
    gains = np.array([2000.0, 800.0, -1800.0])  # step-response contribution of each mode
    A = np.diag(poles)
    B = np.ones((3, 1))
    C = (gains * (1 - poles))[None, :]
    return A, B, C, np.zeros((1, 1))


def relay_sequence(rng: np.random.Generator, n: int, min_hold: int, max_hold: int) -> np.ndarray:
    """0/1 switching with random hold times (what a PRBS relay experiment produces)."""
    u = np.zeros(n)
    k, level = int(rng.integers(min_hold, max_hold)), 1.0
    while k < n:
        hold = int(rng.integers(min_hold, max_hold))
        u[k:k + hold] = level
        level = 1.0 - level
        k += hold
    return u


def loop_simulation(A, B, C, D, u, x0=None):
    """Reference: the state-space recursion, one sample at a time."""
    x = np.zeros(A.shape[0]) if x0 is None else np.array(x0, dtype=float)
    y = np.empty((u.shape[0], C.shape[0]))
    for k in range(u.shape[0]):
        y[k] = C @ x + D @ u[k]
        x = A @ x + B @ u[k]
    return y


def frequency_response(A, B, C, D, omegas):
    n = A.shape[0]
    return np.array([C @ np.linalg.solve(np.exp(1j * w) * np.eye(n) - A, B) + D for w in omegas])


@pytest.mark.parametrize("weighting", ident.WEIGHTINGS)
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_noise_free_random_third_order_two_inputs_recovered_to_1e6(seed, weighting):
    rng = np.random.default_rng(seed)
    A, B, C, D = random_stable_system(rng, 3, 2, 1)
    u = rng.normal(size=(1500, 2))
    y = ident.simulate(A, B, C, D, u)

    model = ident.identify(u, y, 0.01, order=3, weighting=weighting)

    true_markov = ident.markov_parameters(A, B, C, D, 60)
    est_markov = ident.markov_parameters(model.A, model.B, model.C, model.D, 60)
    assert np.max(np.abs(est_markov - true_markov)) <= 1e-6 * np.max(np.abs(true_markov))
    omegas = np.linspace(0.01, np.pi, 25)
    true_tf = frequency_response(A, B, C, D, omegas)
    est_tf = frequency_response(model.A, model.B, model.C, model.D, omegas)
    assert np.max(np.abs(est_tf - true_tf) / np.abs(true_tf)) <= 1e-6
    assert model.fit_pct > 99.9999
    # without --order the singular values leave no doubt: exactly 3 are non-zero
    assert ident.n4sid(u[:1000], y[:1000], weighting=weighting).order == 3


def test_noise_free_relay_input_with_offset_and_initial_state_recovered():
    """0/1 relay inputs (non-zero mean, long holds) and a plant not at rest at the start."""
    rng = np.random.default_rng(7)
    A, B, C, D = random_stable_system(rng, 3, 1, 2)
    u = relay_sequence(rng, 2500, 5, 40)[:, None]
    x0 = np.array([1.0, -2.0, 0.5])
    y = loop_simulation(A, B, C, D, u, x0)

    result = ident.n4sid(u, y, 3)

    true_markov = ident.markov_parameters(A, B, C, D, 60)
    est_markov = ident.markov_parameters(result.A, result.B, result.C, result.D, 60)
    assert np.max(np.abs(est_markov - true_markov)) <= 1e-6 * np.max(np.abs(true_markov))
    y_hat = ident.simulate(result.A, result.B, result.C, result.D, u, result.x0)
    assert np.max(np.abs(y_hat - y)) <= 1e-6 * np.max(np.abs(y))


def test_long_record_factorised_in_chunks_is_still_exact():
    """20000 samples: the LQ factor is built from three column chunks."""
    rng = np.random.default_rng(21)
    A, B, C, D = random_stable_system(rng, 3, 1, 1)
    u = relay_sequence(rng, 20000, 3, 30)[:, None]
    y = ident.simulate(A, B, C, D, u)
    y_noisy = y + 0.1 * rng.normal(size=y.shape)
    i = 4
    L = ident._lq_factor(u, y_noisy, i)
    cols = 20000 - 2 * i + 1
    hankel = np.vstack([np.array([u[k:k + cols, 0] for k in range(2 * i)]),
                        np.array([y_noisy[k:k + cols, 0] for k in range(2 * i)])])
    assert np.allclose(L @ L.T, hankel @ hankel.T / cols, rtol=1e-10, atol=1e-10)

    result = ident.n4sid(u, y, 3)
    true_markov = ident.markov_parameters(A, B, C, D, 60)
    est_markov = ident.markov_parameters(result.A, result.B, result.C, result.D, 60)
    assert np.max(np.abs(est_markov - true_markov)) <= 1e-6 * np.max(np.abs(true_markov))


def test_simulate_matches_the_state_space_recursion():
    rng = np.random.default_rng(11)
    A, B, C, D = random_stable_system(rng, 4, 2, 3)
    u = rng.normal(size=(700, 2))
    x0 = rng.normal(size=4)
    reference = loop_simulation(A, B, C, D, u, x0)
    assert np.allclose(ident.simulate(A, B, C, D, u, x0), reference, rtol=0, atol=1e-10)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_noisy_bench_plant_fits_at_least_95_percent_on_held_out_data(seed):
    rng = np.random.default_rng(seed)
    A, B, C, D = bench_like_plant()
    u = relay_sequence(rng, 4000, 30, 150)[:, None]
    y_true = ident.simulate(A, B, C, D, u)
    y = y_true + 0.02 * np.std(y_true) * rng.normal(size=y_true.shape)

    model = ident.identify(u, y, 0.01, order=3, inputs=["P1"], outputs=["L2"])

    assert model.fit_pct >= 95.0
    # the model is as good as the truth on the held-out data (the noise is what is left)
    n_train = model.samples["train"]
    truth_fit = ident.fit_percent(y[n_train:], y_true[n_train:])[0]
    assert model.fit_pct >= truth_fit - 0.3
    dc_true = (C @ np.linalg.solve(np.eye(3) - A, B) + D)[0, 0]
    dc_est = (model.C @ np.linalg.solve(np.eye(3) - model.A, model.B) + model.D)[0, 0]
    assert dc_est == pytest.approx(dc_true, rel=0.02)
    assert model.samples == {"total": 4000, "train": 2800, "test": 1200}


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_order_selection_picks_3_on_third_order_plants_with_moderate_noise(seed):
    rng = np.random.default_rng(100 + seed)
    plants = {
        "bench": bench_like_plant(),
        "resonant": (
            np.array([[0.8, 0.35, 0.0], [-0.35, 0.8, 0.0], [0.0, 0.0, 0.93]]),
            np.array([[1.0], [0.0], [1.0]]),
            np.array([[1.0, 0.5, 0.7]]),
            np.zeros((1, 1)),
        ),
    }
    for name, (A, B, C, D) in plants.items():
        u = relay_sequence(rng, 4000, 10, 100)[:, None]
        y_true = ident.simulate(A, B, C, D, u)
        y = y_true + 0.05 * np.std(y_true) * rng.normal(size=y_true.shape)  # SNR 26 dB

        model = ident.identify(u, y, 0.01)

        assert model.order == 3, (name, model.order_selection)
        assert model.order_selection["method"] == "bic"
        bic = model.order_selection["bic"]
        assert min(bic, key=bic.get) == "3" and len(bic) == ident.DEFAULT_MAX_ORDER


def test_explicit_order_is_used_even_when_lower_than_the_truth():
    rng = np.random.default_rng(5)
    A, B, C, D = bench_like_plant()
    u = relay_sequence(rng, 3000, 30, 150)[:, None]
    y = ident.simulate(A, B, C, D, u) + rng.normal(size=(3000, 1))
    model = ident.identify(u, y, 0.01, order=2)
    assert model.order == 2 and model.A.shape == (2, 2)
    assert model.order_selection == {"method": "fixed"}


def test_innovation_model_gives_kalman_gain_and_noise_covariance():
    """Data from x+ = A x + B u + K e, y = C x + e: R ~ var(e), noise model 1 + C(zI-A)^-1 K."""
    rng = np.random.default_rng(2)
    A = np.array([[0.9, 0.2, 0.0], [-0.2, 0.9, 0.0], [0.0, 0.0, 0.5]])
    B = np.array([[1.0], [0.5], [1.0]])
    C = np.array([[1.0, 0.0, 1.0]])
    K = np.array([[0.5], [0.2], [0.3]])
    n = 4000
    u = rng.normal(size=(n, 1))
    e = 0.3 * rng.normal(size=n)
    x = np.zeros(3)
    y = np.empty((n, 1))
    for k in range(n):
        y[k] = C @ x + e[k]
        x = A @ x + B[:, 0] * u[k, 0] + K[:, 0] * e[k]

    result = ident.n4sid(u, y, 3)

    assert result.R[0, 0] == pytest.approx(0.09, rel=0.1)
    omegas = [0.05, 0.3, 1.0, 2.5]
    noise_true = frequency_response(A, K, C, np.eye(1), omegas)
    noise_est = frequency_response(result.A, result.K, result.C, np.eye(1), omegas)
    assert np.max(np.abs(noise_est - noise_true) / np.abs(noise_true)) <= 0.15
    assert np.allclose(result.Q, result.Q.T) and np.all(np.linalg.eigvalsh(result.Q) > -1e-12)


def test_detrend_keeps_offsets_in_the_model():
    rng = np.random.default_rng(9)
    A, B, C, D = bench_like_plant()
    u = relay_sequence(rng, 4000, 30, 150)[:, None]
    y_true = ident.simulate(A, B, C, D, u) + 500.0  # a base load the relay does not switch
    y = y_true + 10.0 * rng.normal(size=y_true.shape)

    model = ident.identify(u, y, 0.01, order=3, detrend=True)

    assert model.fit_pct >= 95.0
    assert model.y_offset[0] == pytest.approx(np.mean(y[:2800]))
    assert np.max(np.abs(model.simulate(u)[-1000:] - y_true[-1000:])) < 0.05 * np.ptp(y_true)


def test_model_round_trips_through_its_json_text():
    rng = np.random.default_rng(3)
    A, B, C, D = random_stable_system(rng, 3, 2, 2)
    u = rng.normal(size=(1200, 2))
    y = ident.simulate(A, B, C, D, u) + 0.01 * rng.normal(size=(1200, 2))
    model = ident.identify(u, y, 0.01, order=3, inputs=["P1", "P2"], outputs=["L1", "L2"],
                           command="hil identify x.mcap ...")

    text = dumps_model(model)
    back = loads_model(text)

    for name in ("A", "B", "C", "D", "K", "Q", "R", "S", "u_offset", "y_offset"):
        assert np.array_equal(getattr(back, name), getattr(model, name)), name
    assert back.dt == 0.01 and back.inputs == ("P1", "P2") and back.outputs == ("L1", "L2")
    assert back.order == 3 and back.command == "hil identify x.mcap ..."
    assert back.fit_pct == pytest.approx(model.fit_pct, abs=1e-4)
    document = json.loads(text)
    assert document["format"] == MODEL_FORMAT and document["order"] == 3
    assert set(document["fit_pct_per_output"]) == {"L1", "L2"}
    assert np.allclose(back.simulate(u), model.simulate(u))


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.update(format="something else"), "not a model file"),
        (lambda d: d.update(version=99), "version 99 not supported"),
        (lambda d: d.pop("C"), "lacks the key 'C'"),
        (lambda d: d.update(A=[[1.0, 0.0], [0.0, 1.0]]), "A has shape (2, 2), expected (3, 3)"),
        (lambda d: d.update(dt="fast"), "malformed value"),
        # found by the fuzz campaign: int(Infinity) raised OverflowError, not a clear error
        (lambda d: d.update(order=math.inf), "cannot convert float infinity to integer"),
    ],
)
def test_broken_model_text_raises_a_clear_error(edit, message):
    A, B, C, D = bench_like_plant()
    u = relay_sequence(np.random.default_rng(1), 1000, 20, 60)[:, None]
    y = ident.simulate(A, B, C, D, u) + np.random.default_rng(2).normal(size=(1000, 1))
    document = model_to_dict(ident.identify(u, y, 0.01, order=3))
    edit(document)
    with pytest.raises(IdentificationError, match=re.escape(message)):
        loads_model(json.dumps(document))
    with pytest.raises(IdentificationError, match="not valid JSON"):
        loads_model("{broken")


def _bench_data(n=3000, seed=4):
    rng = np.random.default_rng(seed)
    A, B, C, D = bench_like_plant()
    u = relay_sequence(rng, n, 30, 150)[:, None]
    return u, ident.simulate(A, B, C, D, u) + rng.normal(size=(n, 1))


def test_too_few_samples_for_the_block_rows_is_a_clear_error():
    u, y = _bench_data()
    # 15 block rows, 1 input, 1 output: 2*15*(1+1+1)-1 = 89 training samples needed
    with pytest.raises(IdentificationError, match=r"too few samples.*has 84 samples.*at least 89"):
        ident.identify(u[:120], y[:120], 0.01, order=3)
    with pytest.raises(IdentificationError, match=r"too few samples: 60 for 15 block rows"):
        ident.n4sid(u[:60], y[:60], 3)
    model = ident.identify(u[:1200], y[:1200], 0.01, order=3, block_rows=5)
    assert model.block_rows == 5  # fewer block rows: enough samples again


def slow_motor_data(seed: int, n: int = 6000):
    """A plant whose transient outlasts 15 block rows (modes 50 ms, 200 ms, 600 ms at 10 ms)."""
    rng = np.random.default_rng(seed)
    poles = np.exp(-0.01 / np.array([0.05, 0.2, 0.6]))
    gains = np.array([2000.0, 800.0, -1800.0])
    A, B, C = np.diag(poles), np.ones((3, 1)), (gains * (1 - poles))[None, :]
    u = relay_sequence(rng, n, 100, 400)[:, None]
    return u, ident.simulate(A, B, C, np.zeros((1, 1)), u) + 20 * rng.normal(size=(n, 1))


@pytest.mark.parametrize("seed", [1, 3])
def test_block_rows_are_chosen_by_training_bic_when_not_given(seed):
    u, y = slow_motor_data(seed)
    auto = ident.identify(u, y, 0.01, order=3)
    fixed = ident.identify(u, y, 0.01, order=3, block_rows=15)
    tried = auto.block_rows_selection["bic"]
    assert list(tried) == ["15", "30", "60"]
    assert auto.block_rows == int(min(tried, key=tried.__getitem__)) > 15
    assert auto.fit_pct > fixed.fit_pct + 0.2  # 15 rows (0.15 s) cut the 0.6 s mode short
    assert fixed.block_rows_selection == {"method": "fixed"}
    # a record too short for 60 rows tries the others only
    short = ident.identify(u[:500], y[:500], 0.01, order=3)
    assert list(short.block_rows_selection["bic"]) == ["15", "30"]


def test_constant_input_is_a_clear_error():
    u, y = _bench_data()
    with pytest.raises(IdentificationError, match=r"input 'P1' is constant \(0\).*switch it"):
        ident.identify(np.zeros_like(u), y, 0.01, inputs=["P1"])
    late = u.copy()
    late[:2500] = 0.0  # switches only in the held-out part
    with pytest.raises(IdentificationError, match=r"constant.*in the training part"):
        ident.identify(late, y, 0.01, inputs=["P1"])


def test_nan_in_the_data_is_a_clear_error():
    u, y = _bench_data()
    y[1234, 0] = np.nan
    with pytest.raises(IdentificationError, match=r"output 'L2' has 1 NaN.*first at index 1234"):
        ident.identify(u, y, 0.01, outputs=["L2"])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"order": 20}, "order 20 needs at least 21 block rows"),
        ({"train_fraction": 1.0}, "train fraction must be between 0 and 1"),
        ({"weighting": "magic"}, "weighting must be one of"),
        ({"dt": 0.0}, "sample period must be a positive number"),
    ],
)
def test_bad_settings_are_clear_errors(kwargs, message):
    u, y = _bench_data(1500)
    options = {"dt": 0.01, **kwargs}
    with pytest.raises(IdentificationError, match=message):
        ident.identify(u, y, options.pop("dt"), **options, block_rows=15)


def test_inputs_and_outputs_of_different_length_are_rejected():
    u, y = _bench_data(1500)
    with pytest.raises(IdentificationError, match="1500 samples but outputs 1499"):
        ident.identify(u, y[:-1], 0.01)
