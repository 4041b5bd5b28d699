"""N4SID: held-out fit and identification time of hil's ``controllers.ident`` against the
``nfoursid`` package and SIPPY (``sippy-unipi``, if installed), on the same data.

Data: a synthetic relay-switched 3rd-order plant like the bench's motors (apparent power with an
inrush peak, ~1000 VA steady; 20 ms / 50 ms / 300 ms modes) sampled at 0.01 s, a random 0/1
relay sequence (holds 0.3-1.5 s), measurement noise, 4000 samples (40 s); the first 70 % train,
the rest is held out. Every model is judged the same way: its (A, B, C, D) simulated from rest
over the whole record (the experiment starts at rest), fit 100 (1 - ||y - yhat|| / ||y - mean||)
on the held-out samples. "truth" is the noise-free plant output: about the best fit any model
can reach.

Targets (issue 5): faster than nfoursid with at least its fit. The paper's fits (97.61 % P1,
99.07 % P2, 99.86 % machining, MATLAB n4sid on the real bench) are printed for reference only:
they depend on the bench's noise, which the emulator (a later issue) will model.

Timing: median wall time of REPEATS runs per method, the methods interleaved run by run so that
load from other processes hits them alike. BLAS runs single-threaded for every method (set
before numpy loads): on the shared 2-core machine a busy second core made OpenBLAS's second
thread stall these small factorisations (hil's order-3 run: 9 ms single-threaded, 20-110 ms
with two threads under load). Set OPENBLAS_NUM_THREADS yourself to measure otherwise.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import contextlib  # noqa: E402 - BLAS threads must be set before numpy is imported
import io  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from functools import partial  # noqa: E402

import numpy as np  # noqa: E402

from controllers import ident  # noqa: E402

SAMPLES = 4000
REPEATS = 7
TRAIN_FRACTION = 0.7
ORDER = 3
BLOCK_ROWS = 15
NOISE_LEVELS = (0.02, 0.05, 0.10)  # noise std relative to the output's std
PAPER_FITS = {"P1": 97.61, "P2": 99.07, "machining": 99.86}

Matrices = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def plant() -> Matrices:
    poles = np.exp(-0.01 / np.array([0.02, 0.05, 0.3]))
    gains = np.array([2000.0, 800.0, -1800.0])  # step-response contribution of each mode
    return np.diag(poles), np.ones((3, 1)), (gains * (1 - poles))[None, :], np.zeros((1, 1))


def relay_sequence(rng: np.random.Generator, n: int) -> np.ndarray:
    u = np.zeros(n)
    k, level = int(rng.integers(30, 150)), 1.0
    while k < n:
        hold = int(rng.integers(30, 150))
        u[k:k + hold] = level
        level = 1.0 - level
        k += hold
    return u


def held_out_fit(model: Matrices, u: np.ndarray, y: np.ndarray, n_train: int) -> float:
    y_hat = ident.simulate(*model, u[:, None])
    return float(ident.fit_percent(y[n_train:], y_hat[n_train:])[0])


def timed_interleaved(
    funcs: dict[str, Callable[[], Matrices]], repeats: int
) -> dict[str, tuple[Matrices, float]]:
    """Result of each function and its median wall time in ms, the functions run in turn."""
    results = {name: func() for name, func in funcs.items()}  # warm-up (imports, caches)
    times: dict[str, list[float]] = {name: [] for name in funcs}
    for _ in range(repeats):
        for name, func in funcs.items():
            t0 = time.perf_counter()
            results[name] = func()
            times[name].append((time.perf_counter() - t0) * 1e3)
    return {name: (results[name], statistics.median(times[name])) for name in funcs}


def hil_n4sid(u: np.ndarray, y: np.ndarray, order: int | None) -> Matrices:
    r = ident.n4sid(u[:, None], y[:, None], order, block_rows=BLOCK_ROWS)
    return r.A, r.B, r.C, r.D


def nfoursid_n4sid(u: np.ndarray, y: np.ndarray) -> Matrices:
    import pandas as pd
    from nfoursid.nfoursid import NFourSID

    frame = pd.DataFrame({"u": u, "y": y})
    model = NFourSID(frame, output_columns=["y"], input_columns=["u"],
                     num_block_rows=BLOCK_ROWS)
    model.subspace_identification()
    state_space, _ = model.system_identification(rank=ORDER)
    return state_space.a, state_space.b, state_space.c, state_space.d


def sippy_n4sid(u: np.ndarray, y: np.ndarray) -> Matrices:
    from sippy_unipi import system_identification

    with contextlib.redirect_stdout(io.StringIO()):  # SIPPY prints progress and warnings
        model = system_identification(y[None, :], u[None, :], "N4SID",
                                      SS_fixed_order=ORDER, SS_f=BLOCK_ROWS)
    return (np.asarray(model.A), np.asarray(model.B), np.asarray(model.C),
            np.asarray(model.D))


def available(module: str) -> bool:
    try:
        __import__(module)
    except ImportError:
        return False
    return True


def main() -> None:
    rng = np.random.default_rng(2024)
    true_model = plant()
    u = relay_sequence(rng, SAMPLES)
    y_true = ident.simulate(*true_model, u[:, None])[:, 0]
    n_train = round(SAMPLES * TRAIN_FRACTION)
    methods: dict[str, Callable[[np.ndarray, np.ndarray], Matrices]] = {
        "hil n4sid, order 3": lambda a, b: hil_n4sid(a, b, ORDER),
        "hil n4sid, order selected": lambda a, b: hil_n4sid(a, b, None),
    }
    if not available("nfoursid"):
        raise SystemExit("nfoursid is not installed: pip install -r benchmarks/requirements.txt")
    baseline = "nfoursid 1.0.2 (PO-MOESP), order 3"
    methods[baseline] = nfoursid_n4sid
    if available("sippy_unipi"):
        methods["SIPPY 1.0.1 N4SID, order 3"] = sippy_n4sid
    else:
        print("SIPPY (sippy-unipi) not installed: skipped")

    print(f"plant: 3rd order, relay-switched, dt 0.01 s, {SAMPLES} samples "
          f"({TRAIN_FRACTION:.0%} train), {BLOCK_ROWS} block rows for every method; "
          f"BLAS threads {os.environ['OPENBLAS_NUM_THREADS']}, median of {REPEATS} runs")
    print("paper (MATLAB n4sid, real bench): " + ", ".join(
        f"{name} {fit:.2f} %" for name, fit in PAPER_FITS.items()))
    for noise in NOISE_LEVELS:
        y = y_true + noise * np.std(y_true) * rng.normal(size=SAMPLES)
        truth = float(ident.fit_percent(y[n_train:], y_true[n_train:])[0])
        print(f"\nnoise {noise:.0%} of the output std; truth (noise-free plant) fit "
              f"{truth:.2f} %")
        print(f"{'method':<38} {'fit %':>8} {'time ms':>9}")
        u_train, y_train = u[:n_train], y[:n_train]
        timed = timed_interleaved(
            {name: partial(func, u_train, y_train) for name, func in methods.items()},
            REPEATS,
        )
        fits = {}
        for name, (model, ms) in timed.items():
            fits[name] = held_out_fit(model, u, y, n_train)
            order = f"   (order {model[0].shape[0]})" if "selected" in name else ""
            print(f"{name:<38} {fits[name]:8.2f} {ms:9.1f}{order}")
        ours = "hil n4sid, order 3"
        speedup = timed[baseline][1] / timed[ours][1]
        gain = fits[ours] - fits[baseline]
        verdict = "met" if speedup > 1 and gain >= -0.005 else "NOT met"
        print(f"target (faster than nfoursid, fit at least equal): {verdict} "
              f"({speedup:.1f}x faster, fit {gain:+.2f} points)")


if __name__ == "__main__":
    main()
