"""Position references of the servo axis, their future samples, and modulo-360 handling.

A reference gives the commanded axis position [deg] at any time t [s], scalar or array, so a
controller at tick k (time t) gets the future samples r(k+1|k) .. r(k+H_t|k) the extended
reference trajectory needs in one call: ``position(t + dt * [1, .., H_t])``. References are
continuous (they may exceed 360 deg); :class:`Modulo360` wraps one the way a CNC commands a
modulo axis. The axis is a direct-drive rotary axis working modulo 360 deg (paper, section
III-A): :func:`wrap180` and :class:`AngleUnwrapper` turn wrapped positions back into continuous
ones, assuming less than 180 deg of motion between two samples (60 000 rpm at 500 us).

A run places its reference where the axis starts (:class:`PlacedReference`): on the turn
nearest the start position (the reference is an angle of the spindle), or, relative to the
start, at the start position itself.

Scenarios pair a reference with an optional disturbance torque on the plant input (in mA of
q-axis current): the position-disturbance experiment of Fig. 16 holds a set-point while a
torque larger than the current limit pushes the axis away and is then released.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from hil.controllers.errors import ControllerSetupError


def wrap180(angle_deg: float) -> float:
    """The angle in [-180, 180) equivalent to ``angle_deg`` modulo 360."""
    return (angle_deg + 180.0) % 360.0 - 180.0


class AngleUnwrapper:
    """Turns a stream of modulo-360 angles into a continuous one (steps < 180 deg)."""

    def __init__(self) -> None:
        self._last_raw: float | None = None
        self.value = 0.0

    def reset(self) -> None:
        self._last_raw = None
        self.value = 0.0

    def update(self, raw_deg: float, near: float | None = None) -> float:
        """Continuous angle of ``raw_deg``; the first sample lands within 180 deg of ``near``."""
        if self._last_raw is None:
            anchor = raw_deg if near is None else near
            self.value = anchor + wrap180(raw_deg - anchor)
        else:
            self.value += wrap180(raw_deg - self._last_raw)
        self._last_raw = raw_deg
        return self.value


class Reference(Protocol):
    """Commanded position [deg] as a function of time [s] (scalar or array)."""

    def position(self, t: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class Sine:
    """offset + amplitude * sin(2 pi frequency t) [deg]."""

    amplitude: float = 2.0
    frequency: float = 10.0
    offset: float = 0.0

    def position(self, t: np.ndarray) -> np.ndarray:
        return self.offset + self.amplitude * np.sin(2.0 * math.pi * self.frequency * t)


@dataclass(frozen=True)
class Hold:
    """A constant set-point [deg]."""

    position_deg: float = 0.0

    def position(self, t: np.ndarray) -> np.ndarray:
        return np.full_like(np.asarray(t, dtype=float), self.position_deg)


@dataclass(frozen=True)
class Ramp:
    """Constant velocity ``speed_deg_s`` from ``offset`` [deg] (crosses 360 when long enough)."""

    speed_deg_s: float = 360.0
    offset: float = 0.0

    def position(self, t: np.ndarray) -> np.ndarray:
        return self.offset + self.speed_deg_s * np.asarray(t, dtype=float)


@dataclass(frozen=True)
class Trapezoid:
    """Trapezoidal velocity profile: a ``stroke`` [deg] move at ``speed_rpm`` (Fig. 14); a
    negative stroke moves the other way, the same profile mirrored.

    The paper gives stroke (270 deg) and top speed (60 rpm) but not the acceleration; the
    default 1000 deg/s^2 needs about 350 mA on the published model, "well within" the 1000 mA
    limit as the paper reports for Fig. 14. The move starts at ``start`` [s] from ``offset``.
    """

    stroke: float = 270.0
    speed_rpm: float = 60.0
    acceleration: float = 1000.0
    start: float = 0.05
    offset: float = 0.0

    def __post_init__(self) -> None:
        if self.stroke == 0:
            raise ControllerSetupError("trapezoid: stroke must not be 0 [deg] (negative: a "
                                       "move in the negative direction)")
        for name in ("speed_rpm", "acceleration"):
            if not getattr(self, name) > 0:
                raise ControllerSetupError(
                    f"trapezoid: {name} must be > 0, got {getattr(self, name)}")

    def _phases(self) -> tuple[float, float, float]:
        """(acceleration time, flat time, top speed [deg/s]) of the move's length."""
        length, a = abs(self.stroke), self.acceleration
        t_acc = min(self.speed_rpm * 6.0 / a, math.sqrt(length / a))  # triangular when short
        v_top = a * t_acc
        return t_acc, (length - a * t_acc**2) / v_top, v_top

    def position(self, t: np.ndarray) -> np.ndarray:
        a = self.acceleration
        t_acc, t_flat, v_top = self._phases()
        tau = np.clip(np.asarray(t, dtype=float) - self.start, 0.0, None)
        t1, t2 = t_acc, t_acc + t_flat
        t3 = t2 + t_acc
        up = 0.5 * a * np.minimum(tau, t1) ** 2
        flat = v_top * np.clip(tau - t1, 0.0, t_flat)
        td = np.clip(tau - t2, 0.0, t_acc)
        down = v_top * td - 0.5 * a * td**2
        moved = np.where(tau >= t3, abs(self.stroke), up + flat + down)
        return self.offset + math.copysign(1.0, self.stroke) * moved

    def duration(self) -> float:
        """Time [s] from t = 0 to the end of the move."""
        t_acc, t_flat, _ = self._phases()
        return self.start + 2 * t_acc + t_flat


@dataclass(frozen=True)
class Modulo360:
    """Another reference wrapped into [0, 360), as commanded to a modulo axis."""

    inner: Reference

    def position(self, t: np.ndarray) -> np.ndarray:
        return np.mod(self.inner.position(t), 360.0)


class PlacedReference:
    """A run's reference, placed where the axis starts: ``inner`` + ``offset_deg``, the
    offset fixed by :meth:`place` with the position the drive was enabled at (p0), before
    the first step:

    * by default the reference is an angle of the spindle (the papers' axis): it runs on the
      turn nearest p0, ``offset_deg = 360 k`` with ``k = round((p0 - r(0)) / 360)``;
    * ``relative`` (``from_here``): the reference is a motion from where the axis stands,
      ``offset_deg = p0`` (r'(t) = p0 + r(t));
    * ``absolute`` (a homed axis): the reference is the axis' own position, ``offset_deg =
      0``.

    Sampled before it is placed (a controller that reads its reference when it is built, not
    in ``step``), it raises: the start position is not known yet."""

    def __init__(self, inner: Reference, *, relative: bool = False,
                 absolute: bool = False) -> None:
        self.inner = inner
        self.relative, self.absolute = relative, absolute
        self.offset_deg: float | None = None

    def place(self, start_deg: float) -> float:
        """Fix the offset for an axis that starts at ``start_deg`` (multi-turn); returns it."""
        if self.relative:
            self.offset_deg = float(start_deg)
        elif self.absolute:
            self.offset_deg = 0.0
        else:
            r0 = float(np.asarray(self.inner.position(np.array([0.0])), dtype=float)[0])
            self.offset_deg = 360.0 * round((start_deg - r0) / 360.0)
        return self.offset_deg

    def position(self, t: np.ndarray) -> np.ndarray:
        if self.offset_deg is None:
            raise ControllerSetupError(
                "the run's reference is placed where the axis starts, when the "
      "drive is enabled: a controller samples it in step(), not when "
      "it is built")
        return self.inner.position(t) + self.offset_deg


class ReferenceSamples:
    """r(k T) for tick k, computed a block of ticks at a time (vectorised, constant memory)."""

    def __init__(self, reference: Reference, dt: float, block: int = 2048) -> None:
        self.reference, self.dt, self.block = reference, dt, block
        self._first = -1
        self._values = np.empty(0)

    def __call__(self, tick: int) -> float:
        first = tick - tick % self.block
        if first != self._first:
            ticks = first + np.arange(self.block)
            self._values = np.asarray(self.reference.position(ticks * self.dt), dtype=float)
            self._first = first
        return float(self._values[tick - first])


@dataclass(frozen=True)
class PulseDisturbance:
    """A disturbance torque of ``torque_ma`` (current equivalent) from ``start`` to ``end`` [s]."""

    torque_ma: float = 1200.0
    start: float = 0.1
    end: float = 0.35

    def __call__(self, t: float) -> float:
        return self.torque_ma if self.start <= t < self.end else 0.0


Disturbance = Callable[[float], float]


@dataclass(frozen=True)
class CircleAxis:
    """One axis of a circle of ``radius`` [deg] run at ``feed`` [deg/s] along the path from
    the origin, counter-clockwise: axis 0 is ``R (cos wt - 1)``, axis 1 ``R sin wt``
    (w = feed / R), so both start at rest position 0, the centre at (-R, 0)."""

    radius: float
    feed: float
    axis: int

    def position(self, t: np.ndarray) -> np.ndarray:
        w = self.feed / self.radius
        t = np.asarray(t, dtype=float)
        if self.axis == 0:
            return self.radius * (np.cos(w * t) - 1.0)
        return self.radius * np.sin(w * t)


def contour_error(x_deg: float | np.ndarray, y_deg: float | np.ndarray,
                  radius: float) -> float | np.ndarray:
    """Distance of the points (x, y) from the circle of :class:`CircleAxis` (signed: > 0
    outside), the error a circular test (ISO 230-4) measures."""
    return np.hypot(np.add(x_deg, radius), y_deg) - radius


def parse_circle(spec: str) -> tuple[float, float] | None:
    """``circle:radius=R,feed=F`` -> (R, F) [deg, deg/s]; None for any other reference."""
    kind, _, params = spec.partition(":")
    if kind != "circle":
        return None
    values = {"radius": 2.0, "feed": 20.0}
    for item in filter(None, (p.strip() for p in params.split(","))):
        key, eq, text = item.partition("=")
        if not eq or key not in values:
            raise ControllerSetupError(
                f"reference {spec!r}: bad parameter {item!r} (allowed: feed, "
      "radius)")
        try:
            values[key] = float(text)
        except ValueError:
            raise ControllerSetupError(
                f"reference {spec!r}: {key} must be a number, got {text!r}") from None
        if not (math.isfinite(values[key]) and values[key] > 0):
            raise ControllerSetupError(f"reference {spec!r}: {key} must be a positive number")
    return values["radius"], values["feed"]


@dataclass(frozen=True)
class Scenario:
    """What the axis is asked to do (reference) and what pushes it (disturbance, mA or None)."""

    reference: Reference
    disturbance: Disturbance | None = None


def position_disturbance(hold_deg: float = 0.0, torque_ma: float = 1200.0,
                         start: float = 0.1, end: float = 0.35) -> Scenario:
    """Fig. 16: hold a set-point while a torque above the 1000 mA limit pushes the axis away.

    The paper removes a manual push at 0.35 s; here the push is a torque pulse applied at the
    plant input, 1200 mA by default, so a controller limited to 1000 mA cannot resist it and the
    axis is displaced by roughly 20 deg before the release.
    """
    if not end > start:
        raise ControllerSetupError(f"disturbance: end ({end}) must be after start ({start})")
    return Scenario(Hold(hold_deg), PulseDisturbance(torque_ma, start, end))


_SPECS: dict[str, tuple[Callable[..., Scenario], set[str]]] = {
    "sine": (lambda amplitude=2.0, frequency=10.0, offset=0.0:
             Scenario(Sine(amplitude, frequency, offset)), {"amplitude", "frequency", "offset"}),
    "trapezoid": (lambda stroke=270.0, speed=60.0, acceleration=1000.0, start=0.05, offset=0.0:
                  Scenario(Trapezoid(stroke, speed, acceleration, start, offset)),
                  {"stroke", "speed", "acceleration", "start", "offset"}),
    "hold": (lambda position=0.0: Scenario(Hold(position)), {"position"}),
    "disturbance": (lambda position=0.0, torque=1200.0, start=0.1, end=0.35:
                    position_disturbance(position, torque, start, end),
                    {"position", "torque", "start", "end"}),
}


#: every kind of reference, as a refusal lists them: one axis each, and a path of two axes
KINDS = (*_SPECS, "circle (two axes)")


def parse_scenario(spec: str) -> Scenario:
    """``sine:amplitude=2,frequency=10``, ``trapezoid:stroke=270,speed=60`` (a negative stroke
    moves the other way), ``hold:position=0`` or ``disturbance:torque=1200,start=0.1,end=0.35``
    -> :class:`Scenario` (a circle, of two axes, is :func:`parse_circle`'s)."""
    kind, _, params = spec.partition(":")
    if kind not in _SPECS:
        raise ControllerSetupError(
            f"reference {spec!r}: unknown kind {kind!r} (one of {', '.join(KINDS)})")
    build, allowed = _SPECS[kind]
    values: dict[str, float] = {}
    for item in filter(None, (p.strip() for p in params.split(","))):
        key, eq, text = item.partition("=")
        if not eq or key not in allowed:
            raise ControllerSetupError(f"reference {spec!r}: bad parameter {item!r} "
                             f"(allowed: {', '.join(sorted(allowed))})")
        try:
            values[key] = float(text)
        except ValueError:
            raise ControllerSetupError(
                f"reference {spec!r}: {key} must be a number, got {text!r}") from None
        if not math.isfinite(values[key]):
            raise ControllerSetupError(f"reference {spec!r}: {key} must be finite")
    if kind == "sine" and values.get("frequency", 1.0) <= 0:
        raise ControllerSetupError(f"reference {spec!r}: frequency must be > 0")
    return build(**values)
