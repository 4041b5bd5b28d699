"""A sweep from start to end: skip what ``--resume`` finds done, run the rest on the engine
with a progress bar, keep each row as it comes, then write ``results.csv``, ``best.toml`` (the
best trial's parameters, :mod:`hil.sweep.best`) and ``sweep.png``."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from hil.errors import HilError, UsageError
from hil.sweep.best import BEST_KPI, write_best
from hil.sweep.engine import Engine
from hil.sweep.plot import plot_sweep
from hil.sweep.progress import Progress
from hil.sweep.results import finished_row, save_row, summary, write_csv
from hil.sweep.space import Trial
from hil.sweep.trial import TrialJob, experiment_of, run_trial


@dataclass(frozen=True)
class Sweep:
    """``trials`` of one run kind over the run flags ``base`` (argparse dests), into folder
    ``out``."""

    kind: str
    base: dict[str, Any]
    keys: tuple[str, ...]
    trials: tuple[Trial, ...]
    out: Path
    engine: Engine
    resume: bool = False


def run_sweep(sweep: Sweep, stream: TextIO | None = None) -> dict[str, Any]:
    """Run every trial (the failing ones recorded, never stopping the others); the ``--json``
    document, plus ``csv`` and ``png`` paths."""
    try:
        sweep.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out {sweep.out}: cannot create it: {exc.strerror}") from None
    rows: dict[str, dict[str, Any]] = {}
    jobs = []
    for trial in sweep.trials:
        done = finished_row(sweep.out, trial.name, trial.params) if sweep.resume else None
        if done is not None:
            rows[trial.name] = {**done, "resumed": True}
        else:
            jobs.append(job_of(sweep, trial))
    progress = Progress(len(sweep.trials), stream, skipped=len(rows))

    def on_done(row: dict[str, Any]) -> None:
        rows[row["name"]] = row
        save_row(sweep.out, row)
        progress.update(row)

    start = time.perf_counter()
    workers = sweep.engine.run(run_trial, jobs, on_done) if jobs else 0
    wall = time.perf_counter() - start
    progress.close()
    ordered = [rows[t.name] for t in sweep.trials]
    result = summary(ordered, sweep.engine.name, workers or (sweep.engine.workers or 1), wall)
    csv_path = sweep.out / "results.csv"
    write_csv(csv_path, ordered, sweep.keys)
    result["csv"] = str(csv_path)
    best = write_best(sweep.out / "best.toml", ordered, sweep.kind, f"hil sweep {sweep.kind}")
    result["best"] = {"trial": best["name"], "kpi": BEST_KPI[sweep.kind],
                      "value": best["kpis"][BEST_KPI[sweep.kind]],
                      "params": str(sweep.out / "best.toml")} if best is not None else None
    png = sweep.out / "sweep.png"
    result["png"] = str(png) if plot_sweep(sweep.kind, ordered, sweep.keys, str(png)) else None
    return result


def job_of(sweep: Sweep, trial: Trial) -> TrialJob:
    """The job that runs ``trial`` into its own file in the sweep's folder (recorded in its
    own process on Ray: :mod:`hil.sweep.trial`)."""
    return TrialJob(sweep.kind, sweep.base, trial.name, trial.params,
                    str(sweep.out / f"{trial.name}.mcap"), in_process=not sweep.engine.serial)


def check_trials(sweep: Sweep) -> None:
    """Every trial's run planned before anything starts (the controller spec loaded, configs
    and values checked, as ``hil bench|servo run`` does first): the first bad one is a usage
    error naming the trial, before Ray or any device is touched."""
    for trial in sweep.trials:
        try:
            experiment_of(job_of(sweep, trial)).plan()
        except HilError as exc:
            where = f"trial {trial.name}: " if trial.params else ""
            raise UsageError(f"{where}{exc}") from None


def format_sweep(result: Mapping[str, Any], kind: str, keys: Sequence[str]) -> str:
    """The human table of a sweep: one line per trial, its swept values and main KPIs."""
    kpis = ("J1_VA", "J2_VA", "SEC_VA") if kind == "bench" else (
        "max_error_deg", "rms_error_deg", "cumulative_error_deg", "peak_current_mA")
    widths = [max(8, len(k) + 1) for k in keys]
    header = "".join(f"{k:<{w}}" for k, w in zip(keys, widths, strict=True))
    lines = [f"{header}{'status':<10}" + "".join(f"{k:>22}" for k in kpis)]
    for trial in result["trials"]:
        cells = "".join(f"{_text(trial['params'].get(k)):<{w}}"
                        for k, w in zip(keys, widths, strict=True))
        if trial["status"] == "failed":
            lines.append(f"{cells}{'failed':<10}{trial.get('error', '')}")
            continue
        lines.append(f"{cells}{trial['status']:<10}" + "".join(
            f"{_text(trial['kpis'].get(k)):>22}" for k in kpis))
    failed = sum(t["status"] == "failed" for t in result["trials"])
    lines.append(f"{len(result['trials'])} trials ({failed} failed) on {result['engine']} "
                 f"with {result['workers']} worker(s) in {result['wall_s']:.1f} s; "
                 f"table {result['csv']}" + (f", plot {result['png']}" if result["png"] else "")
                 + (f"; best {result['best']['trial']} ({result['best']['kpi']} "
                    f"{_text(result['best']['value'])}): --params {result['best']['params']}"
                    if result.get("best") else ""))
    return "\n".join(lines)


def _text(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return "-" if value is None else str(value)
