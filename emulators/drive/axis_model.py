"""The emulated drive's axis as a linear model, and a model file read as one (``[emulator] model``
of drive.toml, ``hil emulate drive --model F.json``).

:class:`AxisModel` is the axis as the drive's cycles sample it: with ``x`` the state at the
start of a period and ``u`` the current held over it,

    position at the end of the period = C x + D (u - u_offset) + y_offset
    x at the end of the period        = A x + B (u - u_offset)

A model file reads as ``hil identify --servo`` writes it and as the published axis is printed,
x(k+1) = A x(k) + B (u(k) - u_offset), y(k) = C x(k) + y_offset: y(k) the position at the start
of the period the current u(k) is held over, so its feedthrough D is 0 (a current cannot move
the position it starts from; a file with D != 0 pairs each position with the current that led
to it, and is refused). :meth:`AxisModel.of_state_space` takes it to the drive's form.

A model file fits the axis when it has one input whose field names a current in mA (its name
ends in ``_mA``, e.g. ``command_mA``) and one output whose field names a position in degrees
(ends in ``_deg``, e.g. ``position_deg``). Its period must divide the drive's cycle whole
(:func:`period_problem`); the drive steps it ``cycle / dt`` times per SYNC.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from hil.controllers.ident.model_file import model_file_of
from hil.controllers.servo.model import StateSpaceModel
from hil.emulators.errors import EmulatorSetupError
from hil.emulators.model_file import read_model_file

#: the most an axis model may grow per period (its state matrix's largest eigenvalue, in
#: magnitude): beyond it the axis runs away within seconds (the published axis: 1.0000008)
MAX_GROWTH_PER_PERIOD = 1.001
#: an axis model must stay within MAX_POSITION_DEG for this many periods of this current
#: [mA] from rest (the drive counts positions in increments: beyond, they overflow)
CHECK_PERIODS, CHECK_CURRENT_MA, MAX_POSITION_DEG = 2000, 100_000.0, 1e12
#: the signals a servo recording holds the axis' input and output in (``hil identify`` names)
COMMAND_SIGNAL = "/drive/feedback:command_mA"
POSITION_SIGNAL = "/drive/feedback:position_deg"
CURRENT_UNIT, POSITION_UNIT = "_mA", "_deg"


@dataclass(frozen=True)
class AxisModel:
    """One current in [mA], one position out [deg], sampled at the end of each ``dt`` period
    (see the module). ``source``: the file it was read from ('' : built in)."""

    A: np.ndarray
    B: np.ndarray  # (n, 1)
    C: np.ndarray  # (1, n)
    D: np.ndarray  # (1, 1)
    dt: float
    u_offset: float = 0.0
    y_offset: float = 0.0
    source: str = ""

    @property
    def n_states(self) -> int:
        return self.A.shape[0]

    @classmethod
    def of_state_space(cls, model: StateSpaceModel, u_offset: float = 0.0,
                       y_offset: float = 0.0, source: str = "") -> AxisModel:
        """``model`` (``y(k) = C x(k) + D u(k)``: the position at the start of period k) as
        sampled at the end of each period, the current still held: C A and C B + D."""
        A, B = np.asarray(model.A, float), np.asarray(model.B, float)
        C, D = np.asarray(model.C, float), np.asarray(model.D, float)
        if B.ndim != 2 or B.shape[1] != 1 or C.shape[0] != 1:
            raise ValueError("the axis model must have one input (mA) and one output (deg)")
        with np.errstate(over="ignore", invalid="ignore"):  # a model that runs away: refused
            C_end, D_end = C @ A, C @ B + D.reshape(1, 1)  # by load_axis_model, not warned of
        return cls(A, B, C_end, D_end, float(model.dt), u_offset, y_offset, source)


def axis_model_file(model: StateSpaceModel, note: str = "") -> str:
    """The model file text of a known axis (e.g. the published one with another resonance),
    named by its signals, as ``hil identify --servo`` writes one: what ``[emulator] model`` and
    ``hil emulate drive --model`` load."""
    return model_file_of(model, [COMMAND_SIGNAL], [POSITION_SIGNAL],
                         note=note or "a known axis, not identified")


def load_axis_model(path: str) -> AxisModel:
    """The axis model in the model file at ``path``; EmulatorSetupError naming the file and the
    problem (not readable, not a model file, not one current in mA to one position in deg)."""
    model = read_model_file(path)
    if len(model.inputs) != 1 or len(model.outputs) != 1:
        raise EmulatorSetupError(
            f"{path}: has {len(model.inputs)} input(s) and {len(model.outputs)} output(s); an "
            f"axis model has one input, a current in mA ({COMMAND_SIGNAL}), and one output, a "
            f"position in deg ({POSITION_SIGNAL})")
    _check_unit(path, "input", model.inputs[0], CURRENT_UNIT, "a current in mA", COMMAND_SIGNAL)
    _check_unit(path, "output", model.outputs[0], POSITION_UNIT, "a position in deg",
                POSITION_SIGNAL)
    if np.any(model.D != 0):
        raise EmulatorSetupError(
            f"{path}: its feedthrough D is {model.D[0, 0]:g}, not 0: an axis model pairs each "
            "position with the current held after it (a current cannot move the position it "
            "starts from); identify the axis with 'hil identify F.mcap --servo'")
    axis = AxisModel.of_state_space(
        StateSpaceModel(A=model.A, B=model.B, C=model.C, D=model.D, dt=model.dt),
        float(model.u_offset[0]), float(model.y_offset[0]), os.path.abspath(path))
    problem = runaway_problem(axis)
    if problem:
        raise EmulatorSetupError(f"{path}: {problem}: an emulator cannot run that axis")
    return axis


def runaway_problem(axis: AxisModel) -> str | None:
    """Why ``axis`` cannot be stepped for long (it grows more than
    :data:`MAX_GROWTH_PER_PERIOD` per period, or its position, offsets included, leaves
    :data:`MAX_POSITION_DEG` within :data:`CHECK_PERIODS` of a strong current), or None."""
    growth = float(max(abs(np.linalg.eigvals(axis.A))))
    if not growth <= MAX_GROWTH_PER_PERIOD:
        return f"its state matrix A grows {growth:.6g} times per period (at most " \
               f"{MAX_GROWTH_PER_PERIOD:g}: the axis would run away)"
    x, u = np.zeros(axis.n_states), CHECK_CURRENT_MA - axis.u_offset
    with np.errstate(all="ignore"):
        for _ in range(CHECK_PERIODS):
            position = float((axis.C @ x)[0] + axis.D[0, 0] * u + axis.y_offset)
            x = axis.A @ x + axis.B[:, 0] * u
            if not (np.all(np.isfinite(x)) and abs(position) <= MAX_POSITION_DEG):
                return f"its position leaves +-{MAX_POSITION_DEG:g} deg within " \
                       f"{CHECK_PERIODS} periods of {CHECK_CURRENT_MA / 1000:g} A"
    return None


def _check_unit(path: str, role: str, signal: str, unit: str, what: str, example: str) -> None:
    field = signal.rpartition(":")[2]
    if not field.lower().endswith(unit.lower()):
        raise EmulatorSetupError(f"{path}: its {role} {signal!r} is not {what} (its field must "
                                 f"end in {unit}, e.g. {example})")


def period_problem(model: AxisModel, cycle_period_s: float) -> str | None:
    """Why the drive cannot step ``model`` in a cycle of ``cycle_period_s`` (its period must
    equal the cycle or divide it whole, in ns as the drive counts); None: it can."""
    period_ns, cycle_ns = round(model.dt * 1e9), round(cycle_period_s * 1e9)
    if period_ns > 0 and cycle_ns % period_ns == 0:
        return None
    return (f"its period is {model.dt * 1e6:g} us: the drive's cycle of "
            f"{cycle_period_s * 1e6:g} us must be a whole multiple of it")
