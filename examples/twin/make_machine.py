"""Writes machine_axis.json: "the machine" of the twins guide's "Make a twin of your machine"
(docs/guides/twins.md), an axis other than the servo paper's, for hil's drive emulator to stand for.

A two-mass axis (motor and load coupled by a shaft) whose load is lighter than the published
axis': the load-to-motor inertia ratio is 2 where the published axis' is about 3 (its rigid-
body gain is 2.83 deg/s^2 per mA against an initial 11.4), so the same current accelerates it a
third more; the shaft's resonance is at 560 Hz (published: 440 Hz) with a damping ratio of
0.02. The encoder is on the motor. The continuous model is sampled at 500 us with the current
held over each period (zero-order hold); machine.toml adds friction on top of it.

Run it from this folder: ``python make_machine.py`` (the file it writes is in the repository).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.signal import cont2discrete

from hil.controllers.servo.model import SAMPLE_PERIOD_S, StateSpaceModel
from hil.emulators.drive.axis_model import axis_model_file

INITIAL_GAIN = 11.4      # deg/s^2 per mA: the motor alone (the published axis' C B / (T^2 / 2))
LOAD_RATIO = 2.0         # load inertia / motor inertia
RESONANCE_HZ = 560.0
DAMPING = 0.02


def two_mass_axis(initial_gain: float = INITIAL_GAIN, load_ratio: float = LOAD_RATIO,
                  resonance_hz: float = RESONANCE_HZ, damping: float = DAMPING
                  ) -> StateSpaceModel:
    """Motor position [deg] from current [mA]: states motor angle, motor speed, load angle,
    load speed; motor inertia 1, load ``load_ratio``, shaft stiffness and damping placing the
    resonance at ``resonance_hz`` with ``damping``."""
    motor, load = 1.0, load_ratio
    w = 2 * np.pi * resonance_hz
    stiffness = w ** 2 / (1 / motor + 1 / load)
    friction = 2 * damping * w * motor * load / (motor + load)
    A = np.array([
        [0.0, 1.0, 0.0, 0.0],
        [-stiffness / motor, -friction / motor, stiffness / motor, friction / motor],
        [0.0, 0.0, 0.0, 1.0],
        [stiffness / load, friction / load, -stiffness / load, -friction / load],
    ])
    B = np.array([[0.0], [initial_gain / motor], [0.0], [0.0]])
    C = np.array([[1.0, 0.0, 0.0, 0.0]])
    Ad, Bd, Cd, Dd, _ = cont2discrete((A, B, C, np.zeros((1, 1))), SAMPLE_PERIOD_S, "zoh")
    return StateSpaceModel(A=Ad, B=Bd, C=Cd, D=Dd, dt=SAMPLE_PERIOD_S)


def main() -> None:
    out = Path(__file__).with_name("machine_axis.json")
    out.write_text(axis_model_file(two_mass_axis(), "the machine of the twins guide's "
                                   "example: a two-mass axis (examples/twin/make_machine.py)"))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
