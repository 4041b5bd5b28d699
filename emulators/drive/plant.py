"""The servo axis behind the emulated drive: a discrete state-space model plus the physical extras.

Default model: the servo paper's headstock axis
(``hil.controllers.servo.model.published_axis_model``),
T = 500 us, input q-axis current [mA], output motor position [deg]; or another axis, as an
:class:`~hil.emulators.drive.axis_model.AxisModel` (a model file: ``[emulator] model``), whose
offsets and feedthrough it applies. Around the linear model:

* the amplifier's current limit (the applied current saturates at ``current_limit_ma``);
* optional friction, as an equivalent current opposing the motion: viscous ``b * v`` and
  Coulomb ``Fc * tanh(v / v_smooth)`` (the smoothing avoids chatter at standstill in a discrete
  simulation; below ``v_smooth`` it acts like a viscous term of ``Fc / v_smooth``, which must
  stay moderate: from about 300 mA per deg/s it rings with the published model's resonance);
* an optional external torque disturbance, as an equivalent current: a constant (step or pulse)
  plus a sine over a time window, and a value that can be set at run time (the drive maps it to
  an object, 0x2003, so a scenario can inject it over the wire).

Position is kept continuous in degrees (multi-turn); the encoder reports it modulo one revolution
in increments, like the paper's direct-drive rotary axis. The master unwraps it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hil.controllers.servo.model import StateSpaceModel, published_axis_model
from hil.emulators.drive.axis_model import MAX_GROWTH_PER_PERIOD, AxisModel

DEFAULT_INCREMENTS_PER_REV = 1 << 20


@dataclass(frozen=True)
class Friction:
    """Friction as an equivalent motor current [mA]; all zero (off) by default."""

    viscous_ma_per_deg_s: float = 0.0
    coulomb_ma: float = 0.0
    coulomb_smoothing_deg_s: float = 1.0

    def current_ma(self, velocity_deg_s: float) -> float:
        friction = self.viscous_ma_per_deg_s * velocity_deg_s
        if self.coulomb_ma:
            friction += self.coulomb_ma * math.tanh(velocity_deg_s / self.coulomb_smoothing_deg_s)
        return friction


@dataclass(frozen=True)
class Disturbance:
    """External load torque as an equivalent current [mA]: ``constant_ma`` plus
    ``sine_ma * sin(2 pi sine_hz (t - start_s))`` while ``start_s <= t < end_s`` (a step, a
    pulse, or a vibration). Off by default."""

    constant_ma: float = 0.0
    start_s: float = 0.0
    end_s: float = math.inf
    sine_ma: float = 0.0
    sine_hz: float = 0.0

    def current_ma(self, t_s: float) -> float:
        if not self.start_s <= t_s < self.end_s:
            return 0.0
        value = self.constant_ma
        if self.sine_ma and self.sine_hz:
            value += self.sine_ma * math.sin(2.0 * math.pi * self.sine_hz * (t_s - self.start_s))
        return value


class AxisPlant:
    """The axis, advanced one model period at a time by :meth:`step`."""

    def __init__(
        self,
        model: StateSpaceModel | AxisModel | None = None,
        *,
        current_limit_ma: float = 12_000.0,
        increments_per_rev: int = DEFAULT_INCREMENTS_PER_REV,
        friction: Friction | None = None,
        disturbance: Disturbance | None = None,
    ) -> None:
        self.model = model if model is not None else published_axis_model()
        axis = self.model if isinstance(self.model, AxisModel) \
            else AxisModel.of_state_space(self.model)
        if axis.B.shape[1] != 1 or axis.C.shape[0] != 1:
            raise ValueError("the axis model must have one input (mA) and one output (deg)")
        if not current_limit_ma > 0:
            raise ValueError(f"current limit must be > 0 mA, got {current_limit_ma!r}")
        if int(increments_per_rev) != increments_per_rev or not 2 <= increments_per_rev < 2**31:
            raise ValueError(f"increments per revolution must be in 2..2^31-1, got "
                             f"{increments_per_rev!r}")
        self.axis = axis
        self.dt = float(axis.dt)
        self.current_limit_ma = float(current_limit_ma)
        self.increments_per_rev = int(increments_per_rev)
        self.friction = friction or Friction()
        self.disturbance = disturbance or Disturbance()
        self.extra_disturbance_ma = 0.0  # set at run time (e.g. through the drive's 0x2003)
        n = axis.n_states
        # one product per period: [x(k+1); y(end of period k)] = [[A, B], [C, D]] [x(k); u(k)]
        # (u less u_offset, the position less y_offset)
        self._step_matrix = np.block([[axis.A, axis.B], [axis.C, axis.D]]).astype(float)
        self._n = n
        f, d = self.friction, self.disturbance
        # friction or a configured disturbance: the load is computed every period
        self._configured_load = bool(f.viscous_ma_per_deg_s or f.coulomb_ma
                                     or d.constant_ma or (d.sine_ma and d.sine_hz))
        self.reset()

    def reset(self) -> None:
        """Back to rest at position 0, time 0."""
        axis = self.axis
        self._xu = np.zeros(axis.n_states + 1)  # state, then the input of the period
        self._next = np.zeros_like(self._xu)  # the product's buffer: x(k+1), then y(k+1)
        self.steps = 0
        self.position_deg = axis.y_offset  # state 0: the model's operating point
        self.velocity_deg_s = 0.0
        self.applied_current_ma = 0.0

    @property
    def time_s(self) -> float:
        return self.steps * self.dt

    def load_current_ma(self) -> float:
        """Friction and disturbance right now, as a current opposing the motor [mA]."""
        return (self.friction.current_ma(self.velocity_deg_s)
                - self.disturbance.current_ma(self.time_s) - self.extra_disturbance_ma)

    def saturated(self, current_ma: float) -> float:
        """The current the amplifier applies for ``current_ma``: saturated at the current
        limit, none when it is not finite."""
        limit, applied = self.current_limit_ma, float(current_ma)
        if applied - applied != 0.0:  # not finite: no current
            return 0.0
        if applied > limit:
            return limit
        if applied < -limit:
            return -limit
        return applied

    def step(self, current_ma: float, periods: int = 1) -> None:
        """Apply ``current_ma`` (saturated at the current limit) for ``periods`` model periods."""
        self.applied_current_ma = applied = self.saturated(current_ma)
        xu, z, n = self._xu, self._next, self._n
        product = self._step_matrix.dot  # np.matmul's (the same BLAS call), without a ufunc's cost
        u_offset, y_offset = self.axis.u_offset, self.axis.y_offset
        loaded = self._configured_load or self.extra_disturbance_ma
        for _ in range(periods):
            xu[n] = (applied - self.load_current_ma() if loaded else applied) - u_offset
            product(xu, out=z)
            position = z.item(n) + y_offset
            xu, z = z, xu  # x(k+1) is where the product put it; its last entry takes u(k+1)
            self.velocity_deg_s = (position - self.position_deg) / self.dt
            self.position_deg = position
            self.steps += 1
        self._xu, self._next = xu, z

    def friction_problem(self) -> str | None:
        """Why the friction makes the axis run away, or None. The plant takes the friction of
        the last period's velocity; from some slope at standstill (viscous plus
        ``coulomb / smoothing``) that feedback grows faster than the axis (the published one:
        from ~110 mA per deg/s): the axis, the position a period ago and the one before, with
        the friction's slope, grow more than :data:`MAX_GROWTH_PER_PERIOD` per period."""
        f, axis = self.friction, self.axis
        slope = f.viscous_ma_per_deg_s + f.coulomb_ma / f.coulomb_smoothing_deg_s
        if not slope:
            return None
        n, gain = axis.n_states, -slope / self.dt  # the current per position step
        M = np.zeros((n + 2, n + 2))  # state: x(k), position(k), position(k-1)
        M[:n, :n], M[:n, n], M[:n, n + 1] = axis.A, axis.B[:, 0] * gain, -axis.B[:, 0] * gain
        M[n, :n], M[n, n], M[n, n + 1] = axis.C[0], axis.D[0, 0] * gain, -axis.D[0, 0] * gain
        M[n + 1, n] = 1.0
        growth = float(max(abs(np.linalg.eigvals(M))))
        if growth <= MAX_GROWTH_PER_PERIOD:
            return None
        return (f"makes the axis run away: its slope at standstill, viscous_mA_per_deg_s + "
                f"coulomb_mA / coulomb_smoothing_deg_s = {slope:g} mA/(deg/s), grows it "
                f"{growth:.4g} times per {self.dt * 1e6:g} us period (at most "
                f"{MAX_GROWTH_PER_PERIOD:g})")

    def position_increments(self) -> int:
        """Encoder reading: position in increments modulo one revolution, in [0, increments)."""
        return math.floor(self.position_deg / 360.0 * self.increments_per_rev) \
            % self.increments_per_rev

