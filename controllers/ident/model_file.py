"""The model file of an identified model: its JSON format, written and read.

:func:`dumps_model` / :func:`loads_model` convert an
:class:`~hil.controllers.ident.n4sid.IdentifiedModel` to and from its JSON text (format
``hil.ident.state-space``, its content :func:`model_to_dict`); :func:`json_text` is the
formatter that keeps every matrix row on one line. :func:`model_file_of` writes the file of a
known model (not identified: a model of another machine, for an emulator to run).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from hil.controllers.ident.n4sid import IdentificationError, IdentifiedModel

MODEL_FORMAT = "hil.ident.state-space"
MODEL_FORMAT_VERSION = 1
_NUMBER_LIST = re.compile(r"\[\s*([-+0-9.eEInfinityNa,\s]*?)\s*\]")


def model_to_dict(model: IdentifiedModel) -> dict[str, Any]:
    """The model file content (JSON-able): matrices as nested lists, row-major."""
    return {
        "format": MODEL_FORMAT,
        "version": MODEL_FORMAT_VERSION,
        "equations": "x(k+1) = A x(k) + B (u(k) - u_offset) + w(k), "
        "y(k) = C x(k) + D (u(k) - u_offset) + y_offset + v(k), "
        "cov([w; v]) = [[Q, S], [S^T, R]]; innovation form: w = K e, v = e, "
        "K the steady-state Kalman gain; time step dt seconds",
        "dt": model.dt,
        "order": model.order,
        "inputs": list(model.inputs),
        "outputs": list(model.outputs),
        "fit_pct": round(model.fit_pct, 4),
        "fit_pct_per_output": {
            name: round(float(fit), 4)
            for name, fit in zip(model.outputs, model.fit_pct_per_output, strict=True)
        },
        **{name: getattr(model, name).tolist() for name in ("A", "B", "C", "D", "K")},
        "noise_covariance": {name: getattr(model, name).tolist() for name in ("Q", "R", "S")},
        "u_offset": model.u_offset.tolist(),
        "y_offset": model.y_offset.tolist(),
        "singular_values": model.singular_values.tolist(),
        "block_rows": model.block_rows,
        "samples": dict(model.samples),
        "order_selection": model.order_selection,
        "block_rows_selection": model.block_rows_selection,
        "command": model.command,
        "experiment": model.experiment,
    }


def model_from_dict(data: dict[str, Any]) -> IdentifiedModel:
    """Rebuild a model from :func:`model_to_dict` output; wrong content raises
    IdentificationError."""
    if not isinstance(data, dict) or data.get("format") != MODEL_FORMAT:
        raise IdentificationError(f"not a model file: 'format' must be {MODEL_FORMAT!r}")
    if data.get("version") != MODEL_FORMAT_VERSION:
        raise IdentificationError(
            f"model file version {data.get('version')!r} not supported "
            f"(this hil reads version {MODEL_FORMAT_VERSION})"
        )
    try:
        inputs = tuple(str(x) for x in data["inputs"])
        outputs = tuple(str(x) for x in data["outputs"])
        n, m, ny = int(data["order"]), len(inputs), len(outputs)
        cov = data["noise_covariance"]
        mats = {
            "A": _matrix(data["A"], "A", (n, n)),
            "B": _matrix(data["B"], "B", (n, m)),
            "C": _matrix(data["C"], "C", (ny, n)),
            "D": _matrix(data["D"], "D", (ny, m)),
            "K": _matrix(data["K"], "K", (n, ny)),
            "Q": _matrix(cov["Q"], "noise_covariance.Q", (n, n)),
            "R": _matrix(cov["R"], "noise_covariance.R", (ny, ny)),
            "S": _matrix(cov["S"], "noise_covariance.S", (n, ny)),
        }
        dt = float(data["dt"])
        if not (dt > 0 and math.isfinite(dt)):
            raise IdentificationError(f"model file: dt must be a positive number, got {dt}")
        fits = data.get("fit_pct_per_output", {})
        return IdentifiedModel(
            **mats,
            dt=dt,
            inputs=inputs,
            outputs=outputs,
            u_offset=_vector(data.get("u_offset", [0.0] * m), "u_offset", m),
            y_offset=_vector(data.get("y_offset", [0.0] * ny), "y_offset", ny),
            fit_pct_per_output=np.array([float(fits.get(name, math.nan)) for name in outputs]),
            singular_values=np.asarray(data.get("singular_values", []), dtype=float),
            block_rows=int(data.get("block_rows", 0)),
            samples={k: int(v) for k, v in data.get("samples", {}).items()},
            order_selection=dict(data.get("order_selection", {})),
            block_rows_selection=dict(data.get("block_rows_selection", {})),
            command=str(data.get("command", "")),
            experiment=str(data.get("experiment", "")),
        )
    except IdentificationError:
        raise
    except KeyError as exc:
        raise IdentificationError(f"model file lacks the key {exc.args[0]!r}") from None
    except (TypeError, ValueError, AttributeError, OverflowError) as exc:  # int(Infinity)
        raise IdentificationError(f"model file has a malformed value: {exc}") from None


class LinearSystem(Protocol):
    """A discrete model ``x(k+1) = A x(k) + B u(k)``, ``y(k) = C x(k) + D u(k)`` every ``dt``
    seconds (e.g. :class:`hil.controllers.servo.model.StateSpaceModel`)."""

    @property
    def A(self) -> np.ndarray: ...  # noqa: N802
    @property
    def B(self) -> np.ndarray: ...  # noqa: N802
    @property
    def C(self) -> np.ndarray: ...  # noqa: N802
    @property
    def D(self) -> np.ndarray: ...  # noqa: N802
    @property
    def dt(self) -> float: ...


def model_file_of(model: LinearSystem, inputs: Sequence[str], outputs: Sequence[str], *,
                  u_offset: Sequence[float] | None = None,
                  y_offset: Sequence[float] | None = None, note: str = "") -> str:
    """The model file text of a known model, its matrices as they are (sample ``k`` pairs
    ``u(k)`` and ``y(k)`` as the file's equations say): inputs and outputs named as signals
    (``TOPIC:FIELD``), optional offsets, no noise (K, Q, R, S zero). Its fit is 100 % (the
    model is its own data) and its ``experiment`` says it was not identified (``note``)."""
    A, B = np.atleast_2d(np.asarray(model.A, float)), np.asarray(model.B, float)
    C, D = np.asarray(model.C, float), np.asarray(model.D, float)
    n, m, ny = A.shape[0], len(inputs), len(outputs)
    B, C, D = B.reshape(n, m), C.reshape(ny, n), D.reshape(ny, m)
    zeros = np.zeros
    known = IdentifiedModel(
        A=A, B=B, C=C, D=D, K=zeros((n, ny)), Q=zeros((n, n)), R=zeros((ny, ny)),
        S=zeros((n, ny)), dt=float(model.dt), inputs=tuple(inputs), outputs=tuple(outputs),
        u_offset=np.asarray(u_offset if u_offset is not None else zeros(m), float),
        y_offset=np.asarray(y_offset if y_offset is not None else zeros(ny), float),
        fit_pct_per_output=np.full(ny, 100.0),
        experiment=note or "a known model written by model_file_of, not identified")
    text = dumps_model(known)
    loads_model(text)  # what it wrote reads back (shapes, finite values, dt > 0)
    return text


def dumps_model(model: IdentifiedModel) -> str:
    """The model file text (JSON)."""
    return json_text(model_to_dict(model)) + "\n"


def json_text(document: Any) -> str:
    """Indented JSON with every list of numbers (a matrix row) on one line."""
    text = json.dumps(document, indent=2)
    return _NUMBER_LIST.sub(lambda m: "[" + " ".join(m.group(1).split()) + "]", text)


def loads_model(text: str) -> IdentifiedModel:
    """Parse a model file text; raises IdentificationError naming what is wrong."""
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise IdentificationError(f"model file is not valid JSON: {exc}") from None
    return model_from_dict(data)


def _matrix(value: Any, name: str, shape: tuple[int, int]) -> np.ndarray:
    a = np.asarray(value, dtype=float)
    if a.shape != shape:
        raise IdentificationError(f"model file: {name} has shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise IdentificationError(f"model file: {name} has non-finite entries")
    return a


def _vector(value: Any, name: str, size: int) -> np.ndarray:
    a = np.asarray(value, dtype=float)
    if a.shape != (size,):
        raise IdentificationError(f"model file: {name} has shape {a.shape}, expected ({size},)")
    return a
