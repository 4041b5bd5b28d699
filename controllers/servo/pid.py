"""Cascaded PID baseline of the servo paper (Fig. 12, Table I, eq. 16).

Position P (K_pos, rpm per deg of error) -> velocity PI (K_vel, A per rpm; integral time T_i)
-> notch on the current reference -> current limit. Velocity is the backward difference of the
measured position. Anti-windup: the PI output is clamped to the current limit and the
integrator stops whenever the clamp is active and the error would drive it further.

Reading of eq. (16). Taken literally at T = 500 us, 0.9352(z²-1.9774z+1)/(z²-1.8492z+0.8651)
notches 48 Hz, not the ~440 Hz resonance, has DC gain 1.33, and makes the cascade with the
Table I gains unstable (closed-loop pole |z| = 1.03 at 37 Hz). But it has exactly the form of
the standard second-order notch b = g[1, -2cos w0, 1], a = [1, -2g cos w0, 2g-1] with
g = 1/(1 + tan(bw/2)): g = 0.9352 and cos w0 = 0.9887 reproduce a1 = -1.8492, and only a2
(printed 0.8651, the formula gives 0.8704) breaks the unit DC gain. Its zeros at w0 = 0.1505
rad sit at 440 Hz for a sample period of about 54 us, the rate of a drive's current loop, where
the paper says the filter lives ("Filters" in the current controller). So the notch is read as
that filter: centred on the model's resonance (computed from A_p, 439.8 Hz), quality factor
w0/bw = 1.09 as printed, unit DC gain, discretised at 500 us. With it the Table I gains are
stable on the printed model (largest closed-loop pole |z| = 0.989), and they are kept. (With
no notch at all this discretisation is only just stable: a 487 Hz pole at |z| = 0.998.)

Table I gives no feed-forward, so none is used by default (``velocity_feedforward`` adds that
share of the reference's rate to the velocity set-point: 1 the whole of it, True as 1; the
paper reproduction sweeps it, as a drive's feed-forward the paper does not give).

Other cycle periods. The gains are continuous-time quantities (rpm per deg, A per rpm, T_i in
seconds) and the controller discretises them for its model's T: the velocity is the backward
difference over T, the integrator adds T / T_i of the error per tick and the notch is designed
at T (on the model's resonance as T samples it). Whether the loop stays stable is another
matter: with Table I's T_i = 2 ms it is at 500 us only (|z| = 0.989; at 1 ms the largest
closed-loop pole is 1.06, the integrator adding half the error every tick); T_i = 8 ms holds it
at 1 ms (|z| = 0.979), 16 ms at 2 ms (0.961), and from 5 ms on no T_i does.
:func:`closed_loop_pole` computes it, and :func:`check_stable` refuses an unstable loop naming
a T_i that holds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from hil.controllers.base import TunableParam
from hil.controllers.errors import ControllerSetupError
from hil.controllers.servo.model import StateSpaceModel, published_axis_model
from hil.controllers.servo.references import AngleUnwrapper, Reference, wrap180

RPM_PER_DEG_S = 60.0 / 360.0
EQ16_NUMERATOR = (0.9352, -0.9352 * 1.9774, 0.9352)
EQ16_DENOMINATOR = (1.0, -1.8492, 0.8651)
EQ16_QUALITY = math.acos(1.9774 / 2) / (2 * math.atan(1 / 0.9352 - 1))  # w0 / bw = 1.09


def resonance_hz(model: StateSpaceModel) -> float:
    """Frequency of the model's lightly damped complex mode (the highest-frequency one)."""
    angles = np.abs(np.angle(np.linalg.eigvals(model.A)))
    return float(angles.max() / (2 * math.pi * model.dt))


def notch_coefficients(center_hz: float, quality: float, dt: float) -> tuple[np.ndarray,
                                                                             np.ndarray]:
    """Second-order notch (unit DC gain, zeros on the unit circle at ``center_hz``)."""
    if not 0 < center_hz < 0.5 / dt:
        raise ControllerSetupError(
            f"pid: notch centre {center_hz} Hz must be in (0, {0.5 / dt:g}) Hz")
    if not quality > 0:
        raise ControllerSetupError(f"pid: notch quality factor must be > 0, got {quality}")
    # scipy.signal.iirnotch's design (Orfanidis 11.3, -3 dB bandwidth), written out: importing
    # scipy.signal takes two seconds (its array-API layer parses every docstring), which
    # every PID run paid; the test holds the two to each other
    w0 = 2 * float(center_hz) / (1.0 / dt)
    bw = w0 / float(quality)
    bw, w0 = bw * math.pi, w0 * math.pi
    gain = 1.0 / (1.0 + math.tan(bw / 2.0))
    b = gain * np.asarray([1.0, -2.0 * math.cos(w0), 1.0])
    a = np.asarray([1.0, -2.0 * gain * math.cos(w0), 2.0 * gain - 1.0])
    return b, a


NOTCH_READINGS = ("resonance", "eq16", "none")


@dataclass(frozen=True)
class PidConfig:
    """Table I gains, the notch and the current limit [mA].

    ``notch``: "resonance" (default, the reading above: centre ``notch_hz``, or the model's
    resonance when None, quality ``notch_quality``), "eq16" (the printed coefficients used
    literally at 500 us, unstable) or "none".
    """

    k_pos_rpm_per_deg: float = 3.6111
    k_vel_a_per_rpm: float = 0.4444
    ti_s: float = 2000e-6
    notch: str = "resonance"
    notch_hz: float | None = None
    notch_quality: float = EQ16_QUALITY
    u_max: float = 1000.0
    velocity_feedforward: float = 0.0

    def __post_init__(self) -> None:
        for name in ("k_pos_rpm_per_deg", "k_vel_a_per_rpm", "ti_s", "u_max"):
            if not getattr(self, name) > 0:
                raise ControllerSetupError(f"pid.{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 <= self.velocity_feedforward <= 1.0:
            raise ControllerSetupError(f"pid.velocity_feedforward must be a share in [0, 1] of "
                                       f"the reference's velocity, got "
                                       f"{self.velocity_feedforward}")
        if self.notch not in NOTCH_READINGS:
            raise ControllerSetupError(f"pid.notch must be one of {', '.join(NOTCH_READINGS)}, "
                              f"got {self.notch!r}")


class SecondOrderFilter:
    """y = (b0 + b1 z⁻¹ + b2 z⁻²)/(1 + a1 z⁻¹ + a2 z⁻²) u, direct form II transposed."""

    def __init__(self, b: np.ndarray, a: np.ndarray) -> None:
        b = np.asarray(b, float) / a[0]
        a = np.asarray(a, float) / a[0]
        self.b0, self.b1, self.b2 = (float(v) for v in b)
        self.a1, self.a2 = float(a[1]), float(a[2])
        self.reset()

    def reset(self) -> None:
        self._s1 = self._s2 = 0.0

    def __call__(self, u: float) -> float:
        y = self.b0 * u + self._s1
        self._s1 = self.b1 * u - self.a1 * y + self._s2
        self._s2 = self.b2 * u - self.a2 * y
        return y


class CascadedPid:
    """The incumbent drive controller (a :class:`hil.controllers.base.ServoController`):
    ``step(position_deg, t_s) -> current_mA``."""

    def __init__(self, reference: Reference, config: PidConfig | None = None,
                 model: StateSpaceModel | None = None) -> None:
        self.config = config or PidConfig()
        self.model = model or published_axis_model()
        self.reference = reference
        self.dt = self.model.dt
        self.notch = self._make_notch()
        self._position = AngleUnwrapper()
        self.reset()

    def _make_notch(self) -> SecondOrderFilter | None:
        c = self.config
        if c.notch == "none":
            return None
        if c.notch == "eq16":
            return SecondOrderFilter(np.array(EQ16_NUMERATOR), np.array(EQ16_DENOMINATOR))
        center = resonance_hz(self.model) if c.notch_hz is None else c.notch_hz
        return SecondOrderFilter(*notch_coefficients(center, c.notch_quality, self.dt))

    def reset(self) -> None:
        self._position.reset()
        self._last_y: float | None = None
        self._integral = 0.0  # in rpm (multiplied by K_vel at the output)
        if self.notch:
            self.notch.reset()

    def step(self, position_deg: float, t_s: float) -> float:
        c = self.config
        y = self._position.update(float(position_deg))
        # sampled at a numpy scalar, as the excitation does: a 1-element array costs ~2 us more
        # a step, the same bits
        r = float(self.reference.position(np.float64(t_s)))
        velocity = 0.0 if self._last_y is None else (y - self._last_y) / self.dt * RPM_PER_DEG_S
        self._last_y = y
        v_ref = c.k_pos_rpm_per_deg * wrap180(r - y)
        if c.velocity_feedforward:
            r_next = float(self.reference.position(np.float64(t_s + self.dt)))
            v_ref += c.velocity_feedforward * wrap180(r_next - r) / self.dt * RPM_PER_DEG_S
        e_v = v_ref - velocity
        k = 1000.0 * c.k_vel_a_per_rpm  # mA per rpm
        raw = k * (e_v + self._integral)
        # min(max(x, -u_max), u_max), written out (the same result, NaN included: a step of
        # every axis every tick)
        high = c.u_max
        low = -high
        command = low if low > raw else raw
        command = high if high < command else command
        if command == raw or (raw > 0) != (e_v > 0):  # anti-windup: conditional integration
            self._integral += self.dt / c.ti_s * e_v
        if self.notch:
            command = self.notch(command)
            command = low if low > command else command
            command = high if high < command else command
        return command


    # -- parameters changed while it runs (hil.controllers.base.Tunable) ----------------------
    def tunables(self) -> list[TunableParam]:
        """The gains, the integral time, the notch (with the resonance reading) and the
        current bound, in force now; each applies at once."""
        c = self.config
        params = [
            TunableParam(name, gain_of(c, name), unit, low, high, step, description=text)
            for name, (unit, low, high, step, text) in GAINS.items()] + [
            TunableParam("umax", c.u_max, "mA", 0.0, 32_767.0, 10.0,
                         description="current bound of the PI's clamp"),
        ]
        if c.notch == "resonance":
            params += [
                TunableParam("notch_hz", self.notch_center_hz(), "Hz", 1.0, 0.5 / self.dt, 1.0,
                             description="centre of the notch on the current reference"),
                TunableParam("notch_q", c.notch_quality, "", 0.1, 100.0, 0.01,
                             description="quality factor of the notch (centre / bandwidth)")]
        return params

    def notch_center_hz(self) -> float:
        """The notch's centre [Hz]: as configured, else the model's resonance."""
        return resonance_hz(self.model) if self.config.notch_hz is None else self.config.notch_hz

    def _tuned(self, name: str, value: float) -> PidConfig:
        field = _TUNABLE_FIELDS.get(name)
        if field is None:
            raise ControllerSetupError(f"pid: no tunable parameter {name!r}")
        if name in GAINS:
            return with_gain(self.config, name, value)
        changed: dict[str, Any] = {field: value}
        return replace(self.config, **changed)

    def check_tunable(self, name: str, value: float) -> None:
        """A ControllerSetupError when the change leaves the loop unstable on the model."""
        config = self._tuned(name, value)
        if config.notch == "resonance":
            notch_coefficients(self.notch_center_hz() if config.notch_hz is None
                               else config.notch_hz, config.notch_quality, self.dt)
        check_stable(config, self.model)

    def set_tunable(self, name: str, value: float) -> None:
        """Apply a change between two steps; the integrator and the notch keep their state."""
        self.config = self._tuned(name, value)
        if name in ("notch_hz", "notch_q") and self.notch is not None:
            state = (self.notch._s1, self.notch._s2)
            self.notch = self._make_notch()
            if self.notch is not None:
                self.notch._s1, self.notch._s2 = state


_TUNABLE_FIELDS = {"kp": "k_pos_rpm_per_deg", "kv": "k_vel_a_per_rpm", "ti_us": "ti_s",
                   "umax": "u_max", "notch_hz": "notch_hz", "notch_q": "notch_quality"}
#: the gains as parameters (``--param``, live tuning): unit, range, tuning step, what each is
GAINS = {"kp": ("rpm/deg", 0.0, 100.0, 0.01, "position gain K_pos"),
         "kv": ("A/rpm", 0.0, 10.0, 0.001, "velocity gain K_vel"),
         "ti_us": ("us", 100.0, 1e6, 100.0, "integral time T_i of the velocity PI")}


def gain_of(config: PidConfig, name: str) -> float:
    """The gain ``name`` of :data:`GAINS` in ``config``, in the parameter's unit."""
    value = float(getattr(config, _TUNABLE_FIELDS[name]))
    return value * 1e6 if name == "ti_us" else value


def with_gain(config: PidConfig, name: str, value: float) -> PidConfig:
    """``config`` with the gain ``name`` of :data:`GAINS` at ``value`` (the parameter's
    unit)."""
    changed: dict[str, Any] = {_TUNABLE_FIELDS[name]: value / 1e6 if name == "ti_us" else value}
    return replace(config, **changed)


def closed_loop_pole(config: PidConfig, model: StateSpaceModel) -> float:
    """The largest closed-loop pole magnitude |z| of the cascade on ``model`` (< 1: stable),
    from the controller's own step with the current clamp lifted (the linear loop) around a
    reference at rest. The loop's state: the plant's, then the last position, the integrator
    and the notch's two."""
    n = model.n_states
    linear = replace(config, u_max=math.inf)

    def tick(state: np.ndarray) -> np.ndarray:
        pid = CascadedPid(_AtRest(), linear, model)
        pid._last_y, pid._integral = float(state[n]), float(state[n + 1])
        if pid.notch is not None:
            pid.notch._s1, pid.notch._s2 = float(state[n + 2]), float(state[n + 3])
        x = state[:n]
        u = pid.step(float(model.C[0] @ x), 0.0)
        notch = (pid.notch._s1, pid.notch._s2) if pid.notch is not None else (0.0, 0.0)
        return np.concatenate([model.A @ x + model.B[:, 0] * u,
                               [pid._last_y, pid._integral, *notch]])

    closed = np.column_stack([tick(unit) for unit in np.eye(n + 4)])
    return float(np.abs(np.linalg.eigvals(closed)).max())


def check_stable(config: PidConfig, model: StateSpaceModel) -> None:
    """A ControllerSetupError when the loop is unstable on ``model`` at its period, naming the
    pole, the gains that differ from Table I and what holds it: the value up to which such a
    gain does (:func:`stable_bound`), else an integral time (the configured one doubled until
    it does)."""
    pole = closed_loop_pole(config, model)
    if pole < 1.0:
        return
    period_us = model.dt * 1e6
    table_i = PidConfig()
    changed = [name for name in ("kp", "kv") if gain_of(config, name) != gain_of(table_i, name)]
    gains = [f"{name} = {gain_of(config, name):g} {GAINS[name][0]} (Table I: "
             f"{gain_of(table_i, name):g})" for name in changed]
    message = (f"pid: at a cycle period of {period_us:g} us the loop is unstable on the axis "
               f"model (largest closed-loop pole |z| = {pole:.3f}) with "
               f"{', '.join([*gains, f'T_i = {config.ti_s * 1e6:g} us'])}")
    for name in changed:
        bound = stable_bound(config, model, name, gain_of(table_i, name))
        if bound is not None:
            unit, side = GAINS[name][0], "at most" if bound < gain_of(config, name) else \
                "at least"
            raise ControllerSetupError(
                f"{message}; {name} {side} {bound:.3g} {unit} holds it, e.g. --param "
                f"{name}={_inside(bound, gain_of(config, name)):g}")
    for factor in (2, 4, 8, 16, 32):
        longer = replace(config, ti_s=config.ti_s * factor)
        holds = closed_loop_pole(longer, model)
        if holds < 1.0:
            raise ControllerSetupError(f"{message}; a longer integral time holds it, e.g. --param "
                              f"ti_us={longer.ti_s * 1e6:g} (|z| = {holds:.3f})")
    raise ControllerSetupError(
        f"{message}; no longer integral time holds it: a shorter cycle period "
"does")


def stable_bound(config: PidConfig, model: StateSpaceModel, name: str, stable: float
                 ) -> float | None:
    """The value of gain ``name`` nearest ``config``'s that keeps the loop stable, between
    ``stable`` (a value that does: Table I's) and ``config``'s (one that does not), to 0.1 %;
    None when ``stable`` does not hold it either."""
    if closed_loop_pole(with_gain(config, name, stable), model) >= 1.0:
        return None
    low, high = stable, gain_of(config, name)
    while abs(high - low) > 1e-3 * abs(low):
        middle = (low + high) / 2
        holds = closed_loop_pole(with_gain(config, name, middle), model) < 1.0
        low, high = (middle, high) if holds else (low, middle)
    return low


def _inside(bound: float, unstable: float) -> float:
    """A round value on the stable side of ``bound`` (away from ``unstable``), to two
    significant digits."""
    scale = 10.0 ** (math.floor(math.log10(abs(bound))) - 1) if bound else 1.0
    rounding = math.floor if unstable > bound else math.ceil
    return float(rounding(bound / scale) * scale)


class _AtRest:
    """A reference standing at 0 deg (the linear loop's)."""

    def position(self, t: np.ndarray) -> np.ndarray:
        return np.zeros_like(np.asarray(t, dtype=float))
