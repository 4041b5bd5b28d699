"""What a sweep leaves in ``--out DIR``: per trial ``NAME.mcap`` (the session) and
``NAME.json`` (its row: params, kpis, status, run_status, error), and over all trials
``results.csv``. ``--resume`` reuses the rows of trials that already finished.

Two statuses, kept apart: a trial's ``status`` (``ok``, ``violated``, ``failed``: what the
sweep made of it) and its run's ``run_status`` (the run's own ``status``,
:data:`hil.core.verdict.STATUSES`: ``completed``, ``stopped``...)."""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from hil.errors import UsageError

DONE_STATUSES = ("ok", "violated")   # --resume reruns a failed trial
#: the columns of results.csv that are the trial's own, never a KPI's of the same name
TRIAL_COLUMNS = ("trial", "status", "run_status", "mcap", "error")


def row_path(out: Path, name: str) -> Path:
    return out / f"{name}.json"


def save_row(out: Path, row: Mapping[str, Any]) -> None:
    """Keep one trial's row next to its MCAP (written whole, then renamed)."""
    path = row_path(out, row["name"])
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(row, indent=1, default=str), encoding="utf-8")
    tmp.replace(path)


def finished_row(out: Path, name: str, params: Mapping[str, Any]) -> dict[str, Any] | None:
    """The saved row of trial ``name`` if it finished with the same parameters, else None."""
    path = row_path(out, name)
    try:
        row = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if row.get("status") not in DONE_STATUSES or row.get("params") != json.loads(
            json.dumps(dict(params), default=str)):
        return None
    if not Path(row.get("mcap", "")).is_file():
        return None
    return dict(row)


def flatten(kpis: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Scalar KPIs, nested keys joined by '.' (lists such as ``limits`` left out)."""
    flat: dict[str, Any] = {}
    for key, value in kpis.items():
        if isinstance(value, Mapping):
            flat.update(flatten(value, f"{prefix}{key}."))
        elif not isinstance(value, (list, tuple)):
            flat[f"{prefix}{key}"] = value
    return flat


def run_status_of(row: Mapping[str, Any]) -> str:
    """The run's own status of a trial's row (a row kept before it had one: its KPIs')."""
    return str(row.get("run_status") or row.get("kpis", {}).get("status") or "")


def write_csv(path: Path, rows: Sequence[Mapping[str, Any]], keys: Sequence[str]) -> None:
    """``results.csv``: trial, status (the trial's), run_status (the run's), the swept keys,
    every other scalar KPI, mcap, error: one column each."""
    kpi_columns: list[str] = []
    flats = []
    for row in rows:
        flat = {key: value for key, value in flatten(row.get("kpis", {})).items()
                if key not in TRIAL_COLUMNS and key not in keys}
        flats.append(flat)
        kpi_columns += [c for c in flat if c not in kpi_columns]
    columns = ["trial", "status", "run_status", *keys, *kpi_columns, "mcap", "error"]
    try:
        with path.open("w", newline="", encoding="utf-8") as f:
            writer = csv.DictWriter(f, fieldnames=columns)
            writer.writeheader()
            for row, flat in zip(rows, flats, strict=True):
                writer.writerow({"trial": row["name"], "status": row["status"],
                                 "run_status": run_status_of(row),
                                 **{k: row["params"].get(k, "") for k in keys}, **flat,
                                 "mcap": row.get("mcap", ""), "error": row.get("error", "")})
    except OSError as exc:
        raise UsageError(f"{path}: cannot write the results table: {exc.strerror}") from None


def summary(rows: Iterable[Mapping[str, Any]], engine: str, workers: int,
            wall_s: float) -> dict[str, Any]:
    """The ``--json`` document of a sweep."""
    return {"engine": engine, "workers": workers, "wall_s": round(wall_s, 3),
            "trials": [{"name": r["name"], "params": r["params"], "kpis": r.get("kpis", {}),
                        "mcap": r.get("mcap", ""), "status": r["status"],
                        "run_status": run_status_of(r),
                        **({"error": r["error"]} if r.get("error") else {})}
                       for r in rows]}


def finite(value: Any) -> float | None:
    """``value`` as a float when it is a finite number (for plots)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None
