"""The relay bench of the energy paper as a plant: loads behind relays, a three-phase meter,
resource levels. Pure computation (no I/O, no clock): :meth:`BenchPlant.step` advances it one
``dt`` (0.01 s) with the relay states it had at the start of the step.

Loads (``[plant.*]`` of ``hil/configs/bench.toml``, which documents every choice; the plant is
built from a :class:`PlantSpec` that :mod:`hil.bench.config` reads from it):

* a constant base load, always on;
* first-order loads (the heater M1, the UPS M2): S follows its target with ``tau_on_s`` /
  ``tau_off_s``;
* induction motors (P1, P2): a per-unit equivalent circuit and a speed state, so the inrush
  at switch-on, the spin-up and the coast-down come from the physics, not from a fitted curve;
* an optional disturbance load on a time schedule;
* loads given as a model file (``model = "F.json"``): their apparent power from their relays,
  as an identified model says (:mod:`~hil.emulators.bench.load_model`).

The meter adds the loads per phase (S and P additive), then one seeded noise draw per step;
every register of a step comes from one snapshot. Resource levels follow eq. (10) of the paper
with rates per second integrated every step.
"""

from __future__ import annotations

import functools
import math
import threading
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hil.emulators.bench.load_model import LoadModel
from hil.emulators.errors import EmulatorSetupError

COIL_LOG_LENGTH = 4096

PHASES = ("L1", "L2", "L3")

#: Every meter quantity the plant computes (names used by ``[meter.registers]``).
METER_QUANTITIES = (
    "voltage_l1", "voltage_l2", "voltage_l3", "current_l1", "current_l2", "current_l3",
    "power_w_l1", "power_w_l2", "power_w_l3", "va_l1", "va_l2", "va_l3",
    "var_l1", "var_l2", "var_l3", "pf_l1", "pf_l2", "pf_l3",
    "phase_angle_l1", "phase_angle_l2", "phase_angle_l3",
    "avg_voltage", "avg_current", "sum_current", "total_w", "total_va", "total_var",
    "total_pf", "total_phase_angle", "frequency_hz", "import_kwh", "export_kwh",
)
MODELS = ("first_order", "induction_motor")


# -- what the plant is built from (``[plant]`` of the bench config, read by hil.bench.config) --


@dataclass(frozen=True)
class ConstantLoadSpec:
    """The machine's idle load, always on (``[plant.base]``)."""

    va: float
    pf: float
    phases: tuple[str, ...]   # the load is spread over these phases equally


@dataclass(frozen=True)
class FirstOrderLoadSpec:
    """A load behind a relay whose S follows its target with separate time constants."""

    name: str
    relay: str
    va: float
    pf: float
    tau_on_s: float
    tau_off_s: float
    phases: tuple[str, ...]


@dataclass(frozen=True)
class MotorCircuit:
    """Per-unit equivalent circuit of an induction motor: stator r1 + j x1, magnetising j xm,
    rotor r2 / s + j x2."""

    r1: float
    x1: float
    xm: float
    r2: float
    x2: float


@dataclass(frozen=True)
class MotorSpec:
    """An induction motor behind a relay; its load torque is ``t0 + t2 w^2`` (pu)."""

    name: str
    relay: str
    va: float                 # steady apparent power
    inertia_h_s: float
    circuit: MotorCircuit
    t0: float
    t2: float
    phases: tuple[str, ...]


@dataclass(frozen=True)
class ModelLoadSpec:
    """Loads whose apparent power a model file gives: ``name`` the loads it stands for (each
    load whose table names the file, joined by ``+``), on ``phases`` at power factor ``pf``."""

    name: str
    model: LoadModel
    pf: float
    phases: tuple[str, ...]


@dataclass(frozen=True)
class DisturbanceSpec:
    """The unknown load: on during ``windows`` (plant time), repeated every ``period_s``
    (0 = not repeated)."""

    enabled: bool
    va: float
    pf: float
    tau_s: float
    phases: tuple[str, ...]
    period_s: float
    windows: tuple[tuple[float, float], ...]


@dataclass(frozen=True)
class MeterSpec:
    """The three-phase meter: voltage, noise, frequency, starting energy."""

    voltage_v: float
    voltage_sigma_v: float
    va_sigma: float
    frequency_hz: float
    import_kwh: float


@dataclass(frozen=True)
class ResourceSpec:
    """Resource q: consumed while relay ``consumer`` is on, refilled while ``supplier`` is."""

    name: str
    consumer: str
    supplier: str
    alpha: float
    eta: float
    q0: float
    bounds: tuple[float, float]   # operating range: the controllers' constraint
    limits: tuple[float, float]   # physical range (empty, full): the plant clamps to it
    sigma: float                  # sensor noise


@dataclass(frozen=True)
class PlantSpec:
    """Everything the plant is made of."""

    dt_s: float
    seed: int
    coils: int                    # size of the relay module
    relays: dict[str, int]        # relay name -> coil
    meter: MeterSpec
    base: ConstantLoadSpec
    loads: tuple[FirstOrderLoadSpec | MotorSpec | ModelLoadSpec, ...]
    disturbance: DisturbanceSpec
    resources: tuple[ResourceSpec, ...]


def _phase_weights(phases: Sequence[str]) -> tuple[tuple[int, float], ...]:
    share = 1.0 / len(phases)
    return tuple((PHASES.index(p), share) for p in phases)


class Load:
    """A load on some phases: apparent power ``va`` and power factor ``pf`` after each step."""

    def __init__(self, name: str, coil: int | None, weights: tuple[tuple[int, float], ...]):
        self.name = name
        self.coil = coil
        self.weights = weights
        self.va = 0.0
        self.pf = 1.0

    def step(self, on: bool, dt: float) -> None:
        raise NotImplementedError

    def advance(self, coils: Sequence[bool], before: Sequence[bool], dt: float) -> None:
        """One step with the relays latched for it (``coils``) after those of the step before
        (``before``): a relay's load steps by its own coil."""
        self.step(self.coil is not None and coils[self.coil], dt)


class ConstantLoad(Load):
    """Always on (the machine's idle consumption)."""

    def __init__(self, name: str, va: float, pf: float, weights: tuple[tuple[int, float], ...]):
        super().__init__(name, None, weights)
        self.va, self.pf = va, pf

    def step(self, on: bool, dt: float) -> None:
        return None


class FirstOrderLoad(Load):
    """S moves towards ``va`` (on) or 0 (off) with separate time constants."""

    def __init__(self, name: str, coil: int | None, va: float, pf: float, tau_on_s: float,
                 tau_off_s: float, weights: tuple[tuple[int, float], ...]) -> None:
        super().__init__(name, coil, weights)
        self.rated_va, self.pf = va, pf
        self.tau_on_s, self.tau_off_s = tau_on_s, tau_off_s

    def step(self, on: bool, dt: float) -> None:
        target, tau = (self.rated_va, self.tau_on_s) if on else (0.0, self.tau_off_s)
        self.va = target + (self.va - target) * math.exp(-dt / tau)


class InductionMotor(Load):
    """Per-unit induction motor: equivalent circuit plus rotor speed ``speed`` (1 = synchronous).

    ``2H dw/dt = T_e(s) - (t0 + t2 w^2)`` with slip ``s = 1 - w``, integrated by the midpoint
    rule (the error against a 0.1 ms integration is below 0.1 % of the current). Switched off,
    no current flows and the rotor coasts down against its load. ``va`` is scaled so the steady
    state draws exactly ``rated_va``.
    """

    def __init__(self, spec: MotorSpec, coil: int) -> None:
        super().__init__(spec.name, coil, _phase_weights(spec.phases))
        c = spec.circuit
        self.r1, self.x1, self.xm, self.r2, self.x2 = c.r1, c.x1, c.xm, c.r2, c.x2
        self.t0, self.t2 = spec.t0, spec.t2
        self.inertia_h_s = spec.inertia_h_s
        rated_va = spec.va
        self.speed = 0.0
        self.steady_slip = _steady_slip(self.name, c.r1, c.x1, c.xm, c.r2, c.x2, self.t0, self.t2)
        current, self.steady_pf, _ = self.electrical(self.steady_slip)
        self.va_per_pu = rated_va / current
        self.rated_va = rated_va

    def electrical(self, slip: float) -> tuple[float, float, float]:
        """(stator current pu, power factor, electromagnetic torque pu) at ``slip``."""
        return _electrical(self.r1, self.x1, self.xm, self.r2, self.x2, slip)

    def _load_torque(self, speed: float) -> float:
        return _load_torque(self.t0, self.t2, speed)

    def _acceleration(self, speed: float, on: bool) -> float:
        drive = self.electrical(1.0 - speed)[2] if on else 0.0
        return (drive - self._load_torque(speed)) / (2.0 * self.inertia_h_s)

    def step(self, on: bool, dt: float) -> None:
        k1 = self._acceleration(self.speed, on)
        mid = min(max(self.speed + 0.5 * dt * k1, 0.0), 1.0)
        self.speed = min(max(self.speed + dt * self._acceleration(mid, on), 0.0), 1.0)
        if on:
            current, self.pf, _ = self.electrical(1.0 - self.speed)
            self.va = current * self.va_per_pu
        else:
            self.va = 0.0


def _electrical(r1: float, x1: float, xm: float, r2: float, x2: float, slip: float
                ) -> tuple[float, float, float]:
    """A motor's (stator current pu, power factor, electromagnetic torque pu) at ``slip``."""
    s = max(slip, 1e-9)
    z_rotor = complex(r2 / s, x2)
    z_mag = complex(0.0, xm)
    z_in = complex(r1, x1) + z_mag * z_rotor / (z_rotor + z_mag)
    i_stator = 1.0 / z_in
    i_rotor = i_stator * z_mag / (z_rotor + z_mag)
    return abs(i_stator), z_in.real / abs(z_in), abs(i_rotor) ** 2 * r2 / s


def _load_torque(t0: float, t2: float, speed: float) -> float:
    """A motor's load torque pu at ``speed``: t0 + t2 w^2."""
    return t0 + t2 * speed * speed


@functools.lru_cache(maxsize=64)
def _steady_slip(name: str, r1: float, x1: float, xm: float, r2: float, x2: float, t0: float,
                 t2: float) -> float:
    """Stable operating slip: where T_e = T_load below the breakdown slip (bisection).

    Computed once per motor (2,100 evaluations of the circuit, ~4 ms): every plant built
    from the same bench (each session, each emulator start) has the same motors."""
    def torque(slip: float) -> float:
        return _electrical(r1, x1, xm, r2, x2, slip)[2]

    grid = np.linspace(1e-4, 1.0, 2000)
    torques = [torque(s) for s in grid]
    breakdown = float(grid[int(np.argmax(torques))])
    lo, hi = 1e-6, breakdown
    if torque(hi) <= _load_torque(t0, t2, 1.0 - hi):
        raise EmulatorSetupError(f"key 'plant.loads.{name}': the load torque exceeds the "
                          "motor's breakdown torque, it would never reach speed")
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if torque(mid) < _load_torque(t0, t2, 1.0 - mid):
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


class ModelLoad(Load):
    """A model file's load: S from its relays and their switch-on events (see
    :mod:`~hil.emulators.bench.load_model`); 0 at rest, never below."""

    def __init__(self, spec: ModelLoadSpec, relays: dict[str, int]) -> None:
        super().__init__(spec.name, None, _phase_weights(spec.phases))
        self.pf, self.model = spec.pf, spec.model
        self._inputs = [(relays[relay], start) for relay, start in spec.model.inputs]
        self.x = spec.model.x_rest.copy()

    def advance(self, coils: Sequence[bool], before: Sequence[bool], dt: float) -> None:
        """An event input is 1 in the step its relay is switched on (``dt``: the model's own
        period, checked against the plant's when the file was read)."""
        m = self.model
        u = np.array([float(coils[c] and not (start and before[c])) for c, start in self._inputs])
        u -= m.u_offset
        self.x = m.A @ self.x + m.B @ u
        # a linear model may dip below its rest at a switch-off: no load gives power back
        self.va = max(float(m.C @ self.x + m.D @ u) + m.y_offset - m.rest_va, 0.0)


class ScheduledLoad(FirstOrderLoad):
    """The unknown disturbance: a first-order load switched by a time schedule, not a relay."""

    def __init__(self, spec: DisturbanceSpec) -> None:
        super().__init__("disturbance", None, spec.va, spec.pf, spec.tau_s, spec.tau_s,
                         _phase_weights(spec.phases))
        self.period_s, self.windows, self.enabled = spec.period_s, spec.windows, spec.enabled

    def scheduled_on(self, t_s: float) -> bool:
        if not self.enabled:
            return False
        phase = t_s % self.period_s if self.period_s > 0 else t_s
        return any(start <= phase < end for start, end in self.windows)


@dataclass
class ResourceTank:
    """Level q of a resource as it evolves: consumed while coil ``consumer`` is on, refilled
    while coil ``supplier`` is."""

    name: str
    consumer: int
    supplier: int
    alpha: float
    eta: float
    q: float
    bounds: tuple[float, float]
    limits: tuple[float, float]
    sigma: float

    def step(self, coils: Sequence[bool], dt: float) -> None:
        rate = self.alpha * coils[self.consumer] + self.eta * coils[self.supplier]
        self.q = min(max(self.q + rate * dt, self.limits[0]), self.limits[1])


@dataclass(frozen=True)
class Snapshot:
    """Everything the sensors report after one step (noise included), read-only."""

    step: int
    t_s: float
    meter: dict[str, float]
    levels: dict[str, float]


def _build_load(spec: FirstOrderLoadSpec | MotorSpec | ModelLoadSpec, relays: dict[str, int]
                ) -> Load:
    if isinstance(spec, ModelLoadSpec):
        return ModelLoad(spec, relays)
    coil = relays[spec.relay]
    if isinstance(spec, MotorSpec):
        return InductionMotor(spec, coil)
    return FirstOrderLoad(spec.name, coil, spec.va, spec.pf, spec.tau_on_s, spec.tau_off_s,
                          _phase_weights(spec.phases))


class BenchPlant:
    """The bench: relays in, a :class:`Snapshot` of meter and level sensors out.

    ``set_coils`` may be called from another thread (the Modbus server); the relay states are
    latched at the start of each step, so a write acts from the next step on.
    """

    def __init__(self, spec: PlantSpec, *, seed: int | None = None) -> None:
        """``seed``: measurement noise seed (default: the spec's)."""
        self.dt = spec.dt_s
        self.relays = dict(spec.relays)
        base = spec.base
        self.loads: list[Load] = [
            ConstantLoad("base", base.va, base.pf, _phase_weights(base.phases)),
            *(_build_load(load, self.relays) for load in spec.loads),
        ]
        self.disturbance = ScheduledLoad(spec.disturbance)
        self.resources = [
            ResourceTank(r.name, self.relays[r.consumer], self.relays[r.supplier], r.alpha, r.eta,
                         r.q0, r.bounds, r.limits, r.sigma)
            for r in spec.resources
        ]
        meter = spec.meter
        self.voltage_v, self.voltage_sigma_v = meter.voltage_v, meter.voltage_sigma_v
        self.va_sigma, self.frequency_hz = meter.va_sigma, meter.frequency_hz
        self.import_kwh = meter.import_kwh
        self._rng = np.random.default_rng(spec.seed if seed is None else seed)
        self._lock = threading.Lock()
        self._coils = [False] * spec.coils
        self._applied = [False] * spec.coils
        # (step that first used it, coil, on): the latest COIL_LOG_LENGTH changes (a day-long
        # run must not keep every one)
        self.coil_log: deque[tuple[int, int, bool]] = deque(maxlen=COIL_LOG_LENGTH)
        self.k = 0
        self.extra_va = 0.0  # a load step injected by a fault (pf 1, on the base load's phases)
        self.snapshot = self._measure()

    # -- inputs ----------------------------------------------------------------------------
    @property
    def n_coils(self) -> int:
        return len(self._coils)

    def coils(self) -> list[bool]:
        """The relay module's current coil states (what a FC01 read returns)."""
        with self._lock:
            return list(self._coils)

    def set_coils(self, first: int, values: Sequence[bool]) -> None:
        """Set coils ``first..first+len(values)-1`` (bounds are the caller's to check)."""
        with self._lock:
            self._coils[first:first + len(values)] = [bool(v) for v in values]

    def set_relay(self, name: str, on: bool) -> None:
        """Set a relay by its ``[relays]`` name (tests and scripts)."""
        self.set_coils(self.relays[name], [on])

    # -- dynamics --------------------------------------------------------------------------
    @property
    def t_s(self) -> float:
        return self.k * self.dt

    def step(self) -> Snapshot:
        """Advance one ``dt`` with the relay states latched now; return the new snapshot."""
        with self._lock:
            coils = list(self._coils)
        previous = self._applied
        for i, (before, now) in enumerate(zip(previous, coils, strict=True)):
            if before != now:
                self.coil_log.append((self.k, i, now))
        self._applied = coils
        dt = self.dt
        for load in self.loads:
            load.advance(coils, previous, dt)
        self.disturbance.step(self.disturbance.scheduled_on(self.t_s), dt)
        for resource in self.resources:
            resource.step(coils, dt)
        self.k += 1
        snapshot = self._measure()
        self.import_kwh += snapshot.meter["total_w"] * dt / 3.6e6
        snapshot.meter["import_kwh"] = self.import_kwh
        self.snapshot = snapshot
        return snapshot

    def load_va(self) -> dict[str, float]:
        """Noise-free apparent power of every load (truth, for tests and plots)."""
        return {load.name: load.va for load in [*self.loads, self.disturbance]}

    def true_phase_power(self) -> tuple[list[float], list[float]]:
        """Noise-free (S per phase, P per phase): the additive sums of the loads."""
        va, watts = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        for load in [*self.loads, self.disturbance]:
            for phase, share in load.weights:
                va[phase] += load.va * share
                watts[phase] += load.va * load.pf * share
        if self.extra_va:
            for phase, share in self.loads[0].weights:
                va[phase] += self.extra_va * share
                watts[phase] += self.extra_va * share
        return va, watts

    # -- sensors ---------------------------------------------------------------------------
    def _measure(self) -> Snapshot:
        noise = self._rng.standard_normal(6 + len(self.resources)).tolist()
        va_true, w_true = self.true_phase_power()
        m: dict[str, float] = {}
        volts, amps, watts, vas, vars_ = [], [], [], [], []
        for i, phase in enumerate(("l1", "l2", "l3")):
            v = self.voltage_v + self.voltage_sigma_v * noise[i]
            s_true = va_true[i]
            pf = min(w_true[i] / s_true, 1.0) if s_true > 1e-9 else 1.0
            s = max(s_true + self.va_sigma * noise[3 + i], 0.0) if s_true > 1e-9 else 0.0
            p = s * pf
            q = s * math.sqrt(max(1.0 - pf * pf, 0.0))
            i_a = s / v
            m[f"voltage_{phase}"], m[f"current_{phase}"] = v, i_a
            m[f"power_w_{phase}"], m[f"va_{phase}"], m[f"var_{phase}"] = p, s, q
            m[f"pf_{phase}"] = pf
            m[f"phase_angle_{phase}"] = math.degrees(math.acos(pf))
            volts.append(v)
            amps.append(i_a)
            watts.append(p)
            vas.append(s)
            vars_.append(q)
        m["avg_voltage"] = sum(volts) / 3.0
        m["avg_current"] = sum(amps) / 3.0
        m["sum_current"] = sum(amps)
        m["total_w"], m["total_va"], m["total_var"] = sum(watts), sum(vas), sum(vars_)
        total_pf = min(m["total_w"] / m["total_va"], 1.0) if m["total_va"] > 0 else 1.0
        m["total_pf"] = total_pf
        m["total_phase_angle"] = math.degrees(math.acos(total_pf))
        m["frequency_hz"] = self.frequency_hz
        m["import_kwh"] = self.import_kwh
        m["export_kwh"] = 0.0
        levels = {r.name: r.q + r.sigma * noise[6 + j] for j, r in enumerate(self.resources)}
        return Snapshot(self.k, self.t_s, m, levels)

