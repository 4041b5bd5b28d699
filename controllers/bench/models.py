"""Power models of the bench's loads (energy paper, section III-A and eq. 9), ready for
prediction and estimation.

Models are discrete state-space files identified by :mod:`hil.controllers.ident.n4sid` (N4SID),
in the format of :mod:`hil.controllers.ident.model_file` (``hil.ident.state-space``):
``x(k+1) = A x(k) + B (u(k) - u_offset)``, ``y(k) = C x(k) + D (u(k) - u_offset) + y_offset``,
sampled every ``dt`` (0.01 s). Sample ``k`` of the output is
the meter reading after ``k`` plant steps; ``u(k)`` is the relay state written at that tick and
latched by the plant for the next step (so an identified model has ``D`` close to 0).

Three kinds of use:

* :class:`LinearModel` works in deviation coordinates: state 0 and output ``rest_output`` when
  every input is 0 (relays off), whatever offsets the identification used.
* :class:`DeviceModel` (a peripheral P_j): the input is the relay state ``u`` and the switch-on
  event ``s`` (1 at the first sample the relay is on). A motor draws an inrush at switch-on
  and nothing the instant it is switched off; a linear model of ``u`` alone would predict a
  mirror-image dip at switch-off, which an optimiser exploits to "hide" a start behind a stop.
  A one-input model is therefore rewritten in *switch-on form*: a delayed steady term
  ``V u(k-1)`` plus the transient of its step response, driven by ``s``. A model identified with
  two inputs (relay, start) is used as it is.
* :class:`MachiningModel`: inputs are the machining relays (M1, M2); its output includes the
  machine's base load. The sequence is periodic and known (Assumption 1), so its periodic
  steady state is precomputed once and a prediction is that profile plus the decay of the
  estimated state's deviation from it.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from hil.controllers.bench.problem import MachiningSequence
from hil.controllers.errors import ControllerSetupError
from hil.controllers.ident.model_file import loads_model
from hil.controllers.ident.n4sid import IdentificationError


def relay_input(name: str) -> tuple[str, bool]:
    """A model input's relay and whether it is the switch-on pulse: ``/bench/relays:P1`` ->
    ("P1", False); the pulse as ``hil bench identify`` records it, ``/ident/relays:P1_start``,
    or ``P1:start`` -> ("P1", True)."""
    key = name.split("relays:", 1)[-1]
    if key.endswith(":start"):
        return key.removesuffix(":start"), True
    if key.endswith("_start") and len(key) > len("_start"):
        return key.removesuffix("_start"), True
    return key, False


def _input_key(name: str) -> str:
    """Model input name of a recorded field: ``P1``, or ``P1:start`` for the switch-on pulse
    (:func:`relay_input`)."""
    relay, start = relay_input(name)
    return f"{relay}:start" if start else relay


@dataclass(eq=False)
class LinearModel:
    """A single-output discrete model in deviation coordinates (rest: x = 0, all inputs 0)."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray  # (n,)
    D: np.ndarray  # (m,)
    dt: float
    inputs: tuple[str, ...]
    rest_output: float
    name: str = ""

    @property
    def order(self) -> int:
        return self.A.shape[0]

    def impulse(self, n: int) -> np.ndarray:
        """Impulse responses g (n x inputs): g[0] = D, g[k] = C A^(k-1) B."""
        g = np.zeros((n, len(self.inputs)))
        if n == 0:
            return g
        g[0] = self.D
        x = self.B.copy()
        for k in range(1, n):
            g[k] = self.C @ x
            x = self.A @ x
        return g

    def observability(self, rows: int) -> np.ndarray:
        """Rows ``C A^(r+1)``, r = 0..rows-1 (cached): the free response is this times x."""
        cache = self.__dict__.setdefault("_obs", np.zeros((0, self.order)))
        if cache.shape[0] < rows:
            out = np.empty((rows, self.order))
            x = self.C @ self.A
            for r in range(rows):
                out[r] = x
                x = x @ self.A
            self.__dict__["_obs"] = cache = out
        return cache[:rows]

    def dc_gain(self) -> np.ndarray:
        return self.C @ np.linalg.solve(np.eye(self.order) - self.A, self.B) + self.D

    def simulate(self, u: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
        """Output (absolute) for inputs ``u`` (samples x inputs, absolute)."""
        x = np.zeros(self.order) if x0 is None else np.asarray(x0, float).copy()
        y = np.empty(len(u))
        for k, uk in enumerate(np.asarray(u, float)):
            y[k] = self.C @ x + self.D @ uk + self.rest_output
            x = self.A @ x + self.B @ uk
        return y


def load_linear_model(path: str | os.PathLike[str], name: str = "") -> LinearModel:
    """Read a model file (``hil.controllers.ident.model_file`` format) as a :class:`LinearModel`."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            model = loads_model(f.read())
    except FileNotFoundError:
        raise ControllerSetupError(f"model file {path} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ControllerSetupError(f"model file {path}: cannot read: {exc}") from None
    except IdentificationError as exc:
        raise ControllerSetupError(f"model file {path}: {exc}") from None
    return to_linear_model(model.A, model.B, model.C, model.D, model.dt, model.inputs,
                           model.u_offset, model.y_offset, name or os.path.basename(path), path)


def to_linear_model(A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, dt: float,
                    inputs: Sequence[str], u_offset: np.ndarray, y_offset: np.ndarray,
                    name: str, source: str = "model") -> LinearModel:
    """Deviation form of ``x+ = A x + B (u - u0)``, ``y = C x + D (u - u0) + y0`` (output 0)."""
    A, B = np.asarray(A, float), np.asarray(B, float)
    C, D = np.atleast_2d(np.asarray(C, float)), np.atleast_2d(np.asarray(D, float))
    n = A.shape[0]
    if np.max(np.abs(np.linalg.eigvals(A)), initial=0.0) >= 1.0:
        raise ControllerSetupError(f"{source}: model is not stable (|eig(A)| >= 1): cannot predict")
    u0 = np.asarray(u_offset, float).reshape(-1)
    # rest state: x = A x + B (0 - u0)
    x_rest = np.linalg.solve(np.eye(n) - A, B @ (-u0)) if n else np.zeros(0)
    rest = float(C[0] @ x_rest + D[0] @ (-u0) + np.asarray(y_offset, float).reshape(-1)[0])
    return LinearModel(A, B, C[0].copy(), D[0].copy(), float(dt),
                       tuple(_input_key(i) for i in inputs), rest, name)


@dataclass(frozen=True)
class DeviceModel:
    """A peripheral's power in switch-on form: inputs (u, s), output its own VA (0 at rest)."""

    model: LinearModel  # inputs exactly (relay, start)

    @classmethod
    def from_linear(cls, lin: LinearModel) -> DeviceModel:
        if len(lin.inputs) == 2:
            starts = [k for k, name in enumerate(lin.inputs) if name.endswith("start")]
            if len(starts) != 1:
                raise ControllerSetupError(
                    f"model {lin.name}: a two-input device model needs one input "
           f"named '...start' (the switch-on event), got {lin.inputs}")
            order = [1 - starts[0], starts[0]]
            return cls(LinearModel(lin.A, lin.B[:, order], lin.C, lin.D[order], lin.dt,
                                   tuple(lin.inputs[k] for k in order), 0.0, lin.name))
        if len(lin.inputs) != 1:
            raise ControllerSetupError(f"model {lin.name}: a device model has 1 input (relay) or 2 "
                              f"(relay, start), got {len(lin.inputs)}")
        return cls(switch_on_form(lin))

    @property
    def dt(self) -> float:
        return self.model.dt

    @cached_property
    def steady_va(self) -> float:
        """Power drawn once the transient is over (DC gain of the relay input)."""
        return float(self.model.dc_gain()[0])

    def step_on_response(self, n: int) -> np.ndarray:
        """Output for the relay switched on at sample 0 (u = 1 from 0, s = 1 at 0)."""
        g = self.model.impulse(n)
        return np.cumsum(g[:, 0]) + g[:, 1]

    def peak_va(self, n: int = 500) -> float:
        """Highest point of the switch-on response (inrush)."""
        return float(np.max(self.step_on_response(n)))


def switch_on_form(lin: LinearModel) -> LinearModel:
    """Rewrite a one-input model as ``y(k) = V u(k-1) + transient(s)``.

    The step response of ``lin`` is ``y(0) = D``, ``y(k) = V - C A^k (I - A)^-1 B`` (k >= 1)
    with ``V`` the DC gain: a delay state carries ``V u``, and ``s`` (the switch-on event)
    starts the transient ``-C A^k (I - A)^-1 B`` with ``D`` as its feedthrough. Identical to
    ``lin`` for a switch-on; at switch-off the power drops to 0 at once, as a motor's does.
    """
    A, B, C = lin.A, lin.B[:, 0], lin.C
    n = lin.order
    V = float(lin.dc_gain()[0])
    b = -A @ np.linalg.solve(np.eye(n) - A, B)
    A2 = np.zeros((n + 1, n + 1))
    A2[1:, 1:] = A
    B2 = np.zeros((n + 1, 2))
    B2[0, 0] = 1.0
    B2[1:, 1] = b
    C2 = np.concatenate([[V], C])
    D2 = np.array([0.0, float(lin.D[0])])
    name = lin.inputs[0]
    return LinearModel(A2, B2, C2, D2, lin.dt, (name, f"{name}:start"), 0.0, lin.name)


@dataclass(frozen=True)
class MachiningModel:
    """The machining loads (and base load) driven by the known periodic sequence."""

    model: LinearModel  # inputs reordered to sequence.relays
    sequence: MachiningSequence

    @classmethod
    def from_linear(cls, lin: LinearModel, sequence: MachiningSequence) -> MachiningModel:
        """Inputs must be machining relays (``M1``) or their switch-on events (``M1:start``),
        every machining relay at least once."""
        allowed = set(sequence.relays) | {f"{r}:start" for r in sequence.relays}
        bad = [name for name in lin.inputs if name not in allowed]
        if bad or not set(sequence.relays) <= set(lin.inputs):
            raise ControllerSetupError(
                f"model {lin.name}: inputs {lin.inputs} must be the machining "
       f"relays {sequence.relays} (and optionally RELAY:start)")
        return cls(lin, sequence)

    def inputs_at(self, relays: np.ndarray, previous: np.ndarray) -> np.ndarray:
        """Model inputs (samples x inputs) for machining relay states ``relays`` (samples x
        sequence relays, 0/1), ``previous`` being the states before the first sample."""
        prev = np.vstack([previous, relays[:-1]])
        starts = (relays > 0.5) & (prev < 0.5)
        cols = []
        for name in self.model.inputs:
            relay, _, kind = name.partition(":")
            k = self.sequence.relays.index(relay)
            cols.append(starts[:, k] if kind else relays[:, k])
        return np.column_stack(cols).astype(float)

    @cached_property
    def samples_per_period(self) -> int:
        n = round(self.sequence.period_s / self.model.dt)
        if abs(n * self.model.dt - self.sequence.period_s) > 1e-6:
            raise ControllerSetupError(f"sequence period {self.sequence.period_s} s is not a whole "
                              f"number of model samples ({self.model.dt} s)")
        return n

    @cached_property
    def inputs_per_period(self) -> np.ndarray:
        """Model inputs at every sample of one period of the sequence (N x inputs)."""
        relays = self.sequence.samples(0.0, self.samples_per_period, self.model.dt)
        return self.inputs_at(relays, relays[-1:])

    @cached_property
    def periodic(self) -> tuple[np.ndarray, np.ndarray]:
        """Periodic steady state: (states N x n, outputs N) at every sample of the period."""
        m, N = self.model, self.samples_per_period
        u = self.inputs_per_period
        # x(N) = A^N x(0) + sum A^(N-1-k) B u(k): solve for the periodic x(0)
        x = np.zeros(m.order)
        forced = np.zeros(m.order)
        for k in range(N):
            forced = m.A @ forced + m.B @ u[k]
        AN = np.linalg.matrix_power(m.A, N)
        x = np.linalg.solve(np.eye(m.order) - AN, forced)
        states = np.empty((N, m.order))
        outputs = np.empty(N)
        for k in range(N):
            states[k] = x
            outputs[k] = m.C @ x + m.D @ u[k] + m.rest_output
            x = m.A @ x + m.B @ u[k]
        return states, outputs

    def predict(self, x_hat: np.ndarray, sample: int, rows: int) -> np.ndarray:
        """Outputs at samples ``sample + 1 .. sample + rows`` from state ``x_hat`` at
        ``sample`` (samples counted from the sequence origin)."""
        states, outputs = self.periodic
        N = self.samples_per_period
        idx = (sample + 1 + np.arange(rows)) % N
        deviation = np.asarray(x_hat, float) - states[sample % N]
        return outputs[idx] + self.free_response(deviation, rows)

    def free_response(self, x0: np.ndarray, rows: int) -> np.ndarray:
        """C A^(r+1) x0 for r = 0..rows-1."""
        return self.model.observability(rows) @ np.asarray(x0, float)

