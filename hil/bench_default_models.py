"""Regenerate the EEC's default load models (``hil/configs/models/*.json``) from the emulator.

    python -m hil.bench_default_models [--out hil/configs/models]

A switching experiment on the emulated plant (random relay holds of 1.5-4 s, seeded, with the
meter's noise), then N4SID (``controllers.ident.identify``, order 3) per model:

* ``P1.json``, ``P2.json``: inputs (relay, relay:start), output the motor's VA (the measured
  rest level subtracted); two inputs so the model holds the switch-on inrush without a
  mirror-image dip at switch-off (see :mod:`controllers.bench_models`);
* ``machining.json``: inputs (M1, M1:start, M2, M2:start), output the machine's VA, base
  load as ``y_offset`` (the UPS M2 ramps up in 0.4 s but drops in 0.05 s: the start inputs
  let a linear model hold that asymmetry).

These are stand-ins until models identified over the wire (``hil bench identify``) are shipped.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

import numpy as np

from controllers.ident import dumps_model, identify
from emulators.bench_plant import BenchPlant
from hil.bench_io import load_bench_config

COMMAND = "python -m hil.bench_default_models"


def random_holds(rng: np.random.Generator, n: int, dt: float, lo_s: float, hi_s: float
                 ) -> np.ndarray:
    """A 0/1 signal of ``n`` samples that toggles after random holds in [lo_s, hi_s]."""
    out = np.zeros(n)
    k, state = 0, 0.0
    while k < n:
        hold = round(rng.uniform(lo_s, hi_s) / dt)
        out[k:k + hold] = state
        k += hold
        state = 1.0 - state
    return out


def experiment(relays: dict[str, np.ndarray], seconds: float, seed: int
               ) -> tuple[np.ndarray, float]:
    """Play ``relays`` (name -> 0/1 per sample) on a fresh plant; return (total VA, rest VA).

    ``y[k]`` is the reading after k steps, ``u[k]`` the state written at tick k.
    """
    config = load_bench_config()
    plant = BenchPlant(config, seed=seed)
    n = round(seconds / plant.dt)
    y = np.empty(n)
    for k in range(n):
        y[k] = plant.snapshot.meter["total_va"]
        for name, signal in relays.items():
            plant.set_relay(name, bool(signal[k]))
        plant.step()
    rest = plant.loads[0].va  # the base load, the level with every relay off
    return y, float(rest)


def starts(u: np.ndarray) -> np.ndarray:
    """1 at the first sample of every on-period."""
    prev = np.concatenate([[0.0], u[:-1]])
    return ((u > 0.5) & (prev < 0.5)).astype(float)


def device_model(name: str, seed: int, seconds: float = 240.0) -> str:
    rng = np.random.default_rng(seed)
    dt = 0.01
    u = random_holds(rng, round(seconds / dt), dt, 1.5, 4.0)
    y, rest = experiment({name: u}, seconds, seed)
    model = identify(np.column_stack([u, starts(u)]), y - rest, dt,
                     inputs=(name, f"{name}:start"), outputs=(f"{name}_va",), order=3,
                     feedthrough=False, command=COMMAND)
    return dumps_model(model)


def machining_model(seed: int, seconds: float = 240.0) -> str:
    rng = np.random.default_rng(seed)
    dt = 0.01
    n = round(seconds / dt)
    m1, m2 = random_holds(rng, n, dt, 1.5, 4.0), random_holds(rng, n, dt, 1.5, 4.0)
    y, rest = experiment({"M1": m1, "M2": m2}, seconds, seed)
    u = np.column_stack([m1, starts(m1), m2, starts(m2)])
    model = identify(u, y - rest, dt, inputs=("M1", "M1:start", "M2", "M2:start"),
                     outputs=("machining_va",), order=3, feedthrough=False,
                     command=COMMAND)
    model = dataclasses.replace(model, y_offset=np.array([rest]))
    return dumps_model(model)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "configs",
                                                      "models"))
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    texts = {"P1.json": device_model("P1", 11), "P2.json": device_model("P2", 12),
             "machining.json": machining_model(13)}
    for file, text in texts.items():
        with open(os.path.join(args.out, file), "w", encoding="utf-8") as f:
            f.write(text)
        print(f"wrote {os.path.join(args.out, file)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
