"""An identification experiment as a servo controller: a current excitation plus a weak
stabilising loop that keeps the axis near where it started.

The axis is a double integrator (current -> acceleration): an open-loop excitation would let it
drift away, so a PD loop on the position error (``reference - position``, the reference held
where the run started) adds its share, clamped to ``STABILISER_SHARE`` of the amplitude. Its
bandwidth (a couple of Hz for the published axis) is far below the band of interest (the
resonance near 440 Hz), so above a few Hz the current is the excitation alone. The command is
``amplitude * signal(k) + stabiliser``; its peak is at most ``amplitude * (1 +
STABILISER_SHARE)`` (:func:`peak_current_ma`), which must fit inside the run's current limit:
:func:`check_fits` refuses an amplitude that does not.

The excitation (``kind``), each a periodic signal of peak 1 sampled once a tick:

* ``prbs`` (default) - a maximum-length pseudo-random binary sequence (15-bit LFSR, period
  32767 ticks, 16 s at 500 us), its state started from ``seed``. Chosen because its crest
  factor is 1: every tick uses the whole amplitude, so it puts the most power into the axis
  that a current limit allows (twice a chirp's, about three times a flat multisine's), and its
  spectrum is flat from 1/period up to about 0.44 / T (880 Hz at 500 us), the resonance included.
* ``multisine`` - every harmonic of 0.5 Hz up to 0.45 / T with Schroeder phases (crest factor
  1.65): flat and leakage-free over a 2 s period, a third of the power for the same peak.
* ``chirp`` - a linear sweep from 1 Hz to 0.45 / T over 2 s, repeated (crest factor 1.42):
  each frequency excited in turn, so a held-out part of the record sees only some of them.

Measured on the emulated axis (4 s, 300 mA, lockstep): all three find the resonance (439.86 Hz,
damping 0.0112-0.0113) and the rigid-body gain (2.83 deg/s^2 per mA); the held-out fit of
``hil identify --servo`` is 99.8 % (prbs), 96.9 % (multisine), -44 % (chirp).

Settings (:class:`ExcitationConfig`): ``amplitude_ma`` (default ``DEFAULT_AMPLITUDE_MA``),
``kind``, ``seed`` (prbs), ``kp`` [mA/deg] and ``kd`` [mA per deg/s], the stabiliser's gains
(defaults: about 2 Hz on the published axis). Pure: no I/O; the run clamps and records the
current as any controller's.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hil.controllers.base import UNWRAPPED
from hil.controllers.errors import ControllerSetupError
from hil.controllers.servo.excitation_defaults import (
    DEFAULT_AMPLITUDE_MA,
    DEFAULT_KD_MA_PER_DEG_S,
    DEFAULT_KIND,
    DEFAULT_KP_MA_PER_DEG,
    DEFAULT_SEED,
    KINDS,
    STABILISER_SHARE,
)
from hil.controllers.servo.model import SAMPLE_PERIOD_S
from hil.controllers.servo.references import Reference

VELOCITY_FILTER_HZ = 50.0      # the stabiliser's velocity: the position's difference, filtered
PRBS_BITS = 15                 # LFSR length: period 2^15 - 1 ticks
PRBS_TAPS = (15, 14)           # x^15 + x^14 + 1, a primitive polynomial
PERIODIC_S = 2.0               # the multisine's and the chirp's period
LOWEST_HZ = 1.0 / PERIODIC_S   # the multisine's lowest harmonic
CHIRP_START_HZ = 1.0
TOP_OF_NYQUIST = 0.9           # multisine and chirp end at this share of the Nyquist frequency


def peak_current_ma(amplitude_ma: float) -> float:
    """The largest current the experiment can command [mA]: the excitation's peak and the
    stabiliser's whole share."""
    return amplitude_ma * (1.0 + STABILISER_SHARE)


def largest_amplitude_ma(limit_ma: float) -> float:
    """The largest amplitude whose experiment fits inside ``limit_ma`` [mA]."""
    return limit_ma / (1.0 + STABILISER_SHARE)


def check_fits(amplitude_ma: float, limit_ma: float, flag: str = "amplitude") -> None:
    """A ControllerSetupError in one line, in mA, when the excitation and the stabiliser's
    share do not fit inside the current limit ``limit_ma``."""
    if peak_current_ma(amplitude_ma) > limit_ma:
        raise ControllerSetupError(
            f"{flag} {amplitude_ma:g} mA does not fit inside the current limit of "
            f"{limit_ma:g} mA with the stabiliser's share ({STABILISER_SHARE:.0%} of it, "
            f"{amplitude_ma * STABILISER_SHARE:g} mA): at most "
            f"{math.floor(largest_amplitude_ma(limit_ma)):g} mA")


def prbs(seed: int = DEFAULT_SEED) -> np.ndarray:
    """One period of the maximum-length sequence (+-1), the LFSR started at state ``seed``
    (taken modulo the period; a multiple of it counts as 1)."""
    period = (1 << PRBS_BITS) - 1
    state = seed % period or 1
    out = np.empty(period)
    a, b = PRBS_TAPS[0] - 1, PRBS_TAPS[1] - 1
    for k in range(period):
        bit = ((state >> a) ^ (state >> b)) & 1
        out[k] = 1.0 if state & 1 else -1.0
        state = ((state << 1) | bit) & period
    return out


def multisine(dt: float) -> np.ndarray:
    """One period of the Schroeder-phased multisine, scaled to peak 1."""
    n = round(PERIODIC_S / dt)
    top = TOP_OF_NYQUIST * 0.5 / dt
    count = int(top / LOWEST_HZ)
    k = np.arange(1, count + 1)
    phases = -np.pi * k * (k - 1) / count
    t = np.arange(n) * dt
    signal = np.cos(2 * np.pi * LOWEST_HZ * np.outer(t, k) + phases).sum(axis=1)
    return np.asarray(signal / np.max(np.abs(signal)))


def chirp(dt: float) -> np.ndarray:
    """One period of the linear sweep (sine of peak 1)."""
    n = round(PERIODIC_S / dt)
    t = np.arange(n) * dt
    top = TOP_OF_NYQUIST * 0.5 / dt
    rate = (top - CHIRP_START_HZ) / PERIODIC_S
    return np.asarray(np.sin(2 * np.pi * (CHIRP_START_HZ * t + 0.5 * rate * t * t)))


def excitation_signal(kind: str, dt: float, seed: int = DEFAULT_SEED) -> np.ndarray:
    """One period of excitation ``kind`` at the tick ``dt`` [s], peak 1."""
    makers: dict[str, Callable[[], np.ndarray]] = {
        "prbs": lambda: prbs(seed), "multisine": lambda: multisine(dt),
        "chirp": lambda: chirp(dt)}
    if kind not in makers:
        raise ControllerSetupError(f"excitation {kind!r}: expected one of {', '.join(KINDS)}")
    return makers[kind]()


class Stabiliser:
    """A PD loop on ``reference - position`` with a filtered difference for the velocity, its
    current clamped to +-``share_ma``."""

    def __init__(self, kp: float, kd: float, share_ma: float, dt: float) -> None:
        self.kp, self.kd, self.share_ma, self.dt = kp, kd, share_ma, dt
        self.alpha = 1.0 - math.exp(-2 * math.pi * VELOCITY_FILTER_HZ * dt)
        self._last: float | None = None
        self._velocity = 0.0

    def step(self, error_deg: float) -> float:
        """The stabilising current [mA] for ``error_deg`` = reference - position."""
        if self._last is not None:
            raw = (error_deg - self._last) / self.dt
            self._velocity += self.alpha * (raw - self._velocity)
        self._last = error_deg
        u = self.kp * error_deg + self.kd * self._velocity
        return min(max(u, -self.share_ma), self.share_ma)


@dataclass(frozen=True)
class ExcitationConfig:
    """The experiment's settings: ``amplitude_ma`` [mA], ``kind`` (:data:`KINDS`), ``seed``
    (prbs), the stabiliser's ``kp`` [mA/deg] and ``kd`` [mA per deg/s]."""

    amplitude_ma: float = DEFAULT_AMPLITUDE_MA
    kind: str = DEFAULT_KIND
    seed: int = DEFAULT_SEED
    kp: float = DEFAULT_KP_MA_PER_DEG
    kd: float = DEFAULT_KD_MA_PER_DEG_S


class Excitation:
    """The experiment: ``amplitude * signal(k) + stabiliser(reference(t) - position)``; its
    peak must fit inside ``limit_ma`` (:func:`check_fits`), ``dt`` is the tick [s]."""

    position_input = UNWRAPPED

    def __init__(self, reference: Reference, config: ExcitationConfig,
                 limit_ma: float, dt: float = SAMPLE_PERIOD_S) -> None:
        check_fits(config.amplitude_ma, limit_ma)
        self.config, self.reference, self.dt = config, reference, dt
        self.signal = excitation_signal(config.kind, dt, config.seed)
        self.stabiliser = Stabiliser(config.kp, config.kd,
                                     config.amplitude_ma * STABILISER_SHARE, dt)

    def step(self, position_deg: float, t_s: float) -> float:
        k = round(t_s / self.dt) % len(self.signal)
        excitation = self.config.amplitude_ma * float(self.signal[k])
        target = float(self.reference.position(np.float64(t_s)))
        return excitation + self.stabiliser.step(target - position_deg)
