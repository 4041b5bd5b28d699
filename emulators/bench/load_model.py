"""A load of the bench as a model file (``[plant.loads.NAME] model = "F.json"``): its apparent
power [VA] from its relays, as ``hil bench identify`` records them and ``hil identify`` models
them.

The model's inputs are relays and their switch-on events, named as ``/ident/relays`` holds them
(``/ident/relays:P1``: the relay's state, ``/ident/relays:P1_start``: 1 in the step it is
switched on; any topic, the field names the relay); its one output is an apparent power in VA
(``/bench/power:va_l2``, ``total_va``...). Its samples pair as the experiment's do: the input of
step k is the relay state latched for it, the output the meter reading at its start, so

    x(k+1) = A x(k) + B (u(k) - u_offset),  S = C x + D (u - u_offset) + y_offset - rest

(``D`` with the inputs of the step just run: identified bench models have D = 0). The load's S is
the model's output less its ``rest`` (all relays off, held: the state it starts in), never below
0 (a linear model's dip at a switch-off gives no power back), so a model
whose output includes the machine's base load adds only what its relays switch; the base load
stays ``[plant.base]``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from hil.controllers.bench.models import relay_input
from hil.emulators.errors import EmulatorSetupError
from hil.emulators.model_file import read_model_file

VA_FIELDS = ("total_va", "va_l1", "va_l2", "va_l3")


@dataclass(frozen=True)
class LoadModel:
    """A model file's load: ``inputs`` are (relay, switch-on event?) in the model's order."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray  # (n,)
    D: np.ndarray  # (m,)
    dt: float
    inputs: tuple[tuple[str, bool], ...]
    u_offset: np.ndarray
    y_offset: float
    x_rest: np.ndarray  # the state with every input 0, held
    rest_va: float      # the output then
    source: str

    @property
    def relays(self) -> tuple[str, ...]:
        """The relays it reads, each once, in order."""
        return tuple(dict.fromkeys(relay for relay, _ in self.inputs))


def is_apparent_power(signal: str) -> bool:
    """Whether ``signal``'s field names an apparent power in VA (``total_va``, ``va_l2``...)."""
    field = signal.rpartition(":")[2].lower()
    return field in VA_FIELDS or field.endswith("_va")


def load_load_model(path: str) -> LoadModel:
    """The load in the model file at ``path``; EmulatorSetupError naming the file and the
    problem (not readable, not a model file, not relays to one power in VA, not stable)."""
    model = read_model_file(path)
    if len(model.outputs) != 1 or not is_apparent_power(model.outputs[0]):
        raise EmulatorSetupError(
            f"{path}: its outputs {list(model.outputs)} are not one apparent power in VA (a "
            f"load model has one output whose field names VA: {', '.join(VA_FIELDS)}, as "
            "/bench/power records them)")
    if not model.inputs:
        raise EmulatorSetupError(f"{path}: has no input (a load model's inputs are relays, "
                                 "e.g. /ident/relays:P1 and /ident/relays:P1_start)")
    A, B = model.A, model.B
    n = A.shape[0]
    if n and np.max(np.abs(np.linalg.eigvals(A))) >= 1.0:
        raise EmulatorSetupError(f"{path}: is not stable (|eig(A)| >= 1): a load's power must "
                                 "settle")
    u0 = model.u_offset
    x_rest = np.linalg.solve(np.eye(n) - A, B @ (-u0)) if n else np.zeros(0)
    rest = float(model.C[0] @ x_rest + model.D[0] @ (-u0) + model.y_offset[0])
    return LoadModel(A, B, model.C[0].copy(), model.D[0].copy(), model.dt,
                     tuple(relay_input(name) for name in model.inputs), u0,
                     float(model.y_offset[0]), x_rest, rest, os.path.abspath(path))


def period_problem(model: LoadModel, step_s: float) -> str | None:
    """Why the plant cannot step ``model`` once per step of ``step_s``; None: it can."""
    if abs(model.dt - step_s) <= 1e-9 * step_s:
        return None
    return f"its period is {model.dt:g} s: the plant steps every {step_s:g} s (plant.dt_s)"


def missing_relays(model: LoadModel, relays: tuple[str, ...]) -> list[str]:
    """The relays ``model`` reads that are not among ``relays`` (the bench's)."""
    return [relay for relay in model.relays if relay not in relays]
