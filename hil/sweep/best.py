"""A sweep's best trial as ``best.toml``, the file ``hil bench|servo run --params F.toml``
reads: where a sweep ends, a run (or a live tuning session) starts.

The best trial is the one, among those that ran and held their limits (status ``ok``), with
the smallest :data:`BEST_KPI` of its kind (servo: the RMS tracking error; bench: the energy
per piece). Its swept controller parameters (``param.NAME``) are the file's keys; the run
options it swept (``--umax``, ``--gamma1``...) are not controller parameters, and are named in
a comment as the flags to give with it."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from hil.errors import UsageError
from hil.sweep.space import PARAM_PREFIX

#: the KPI a sweep's best trial has the smallest of, by run kind
BEST_KPI = {"servo": "rms_error_deg", "bench": "SEC_VA"}


def best_row(rows: Sequence[Mapping[str, Any]], kind: str) -> Mapping[str, Any] | None:
    """The trial with the smallest :data:`BEST_KPI` among those with status ``ok``."""
    key = BEST_KPI[kind]
    scored = [(row["kpis"][key], i) for i, row in enumerate(rows)
              if row.get("status") == "ok" and _number(row.get("kpis", {}).get(key))]
    return rows[min(scored)[1]] if scored else None


def write_best(path: Path, rows: Sequence[Mapping[str, Any]], kind: str,
               command: str) -> Mapping[str, Any] | None:
    """Write ``best.toml`` for the best trial of ``rows`` (none: no file); that trial."""
    row = best_row(rows, kind)
    if row is None:
        return None
    key = BEST_KPI[kind]
    params = {k[len(PARAM_PREFIX):]: v for k, v in row["params"].items()
              if k.startswith(PARAM_PREFIX)}
    options = {k: v for k, v in row["params"].items() if not k.startswith(PARAM_PREFIX)}
    lines = [f"# the best trial of `{command}`: {row['name']}, {key} = {row['kpis'][key]!r}",
             "# (the smallest of the trials that held their limits). Run it again with",
             f"# hil {kind} run ... --params best.toml"
             + "".join(f" --{k.replace('_', '-')} {v}" for k, v in options.items())]
    lines += [f"{name} = {_toml_value(value)}" for name, value in params.items()]
    try:
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    except OSError as exc:
        raise UsageError(f"{path}: cannot write the best trial: {exc.strerror}") from None
    return row


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) \
        and math.isfinite(value)


def _toml_value(value: Any) -> str:
    """A TOML value: numbers and booleans as such, anything else as a string."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    return json.dumps(str(value))
