"""One trial: the options of ``hil bench|servo run`` with the swept values laid over them, run
in lockstep into its own MCAP file. Runs in a Ray worker or in this process alike."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from hil.core.errors import HilError
from hil.sweep.space import PARAM_PREFIX


@dataclass(frozen=True)
class TrialJob:
    """Everything a worker needs: the run kind, the run's parsed flags and how to make the
    run's options of them (the command line's own function), the swept values."""

    kind: str
    build: Callable[[argparse.Namespace], Any]   # flags -> BenchRunOptions | ServoRunConfig
    base: dict[str, Any]   # vars() of the parsed run flags
    name: str
    params: dict[str, Any]
    mcap: str


def namespace_of(base: Mapping[str, Any], params: Mapping[str, Any]) -> argparse.Namespace:
    """The run's flags with ``params`` laid over them (``param.NAME`` over ``--param``)."""
    args = argparse.Namespace(**base)
    controller_params = dict(args.param)
    for key, value in params.items():
        if key.startswith(PARAM_PREFIX):
            controller_params[key[len(PARAM_PREFIX):]] = value
        else:
            setattr(args, key, value)
    args.param = list(controller_params.items())
    return args


def run_trial(job: TrialJob) -> dict[str, Any]:
    """Run ``job``; its result row (status ``ok``, ``violated`` when a --limit does not hold,
    or ``failed`` with the error). Never raises for a failing run."""
    start = time.perf_counter()
    row: dict[str, Any] = {"name": job.name, "params": job.params, "mcap": job.mcap}
    try:
        args = namespace_of(job.base, job.params)
        args.out = job.mcap
        kpis = execute(job.kind, job.build(args))
    except HilError as exc:
        row.update(status="failed", error=str(exc), kpis={})
    except Exception as exc:  # a trial's bug must not stop the sweep: it is recorded
        row.update(status="failed", error=f"{type(exc).__name__}: {exc}", kpis={})
    else:
        row.update(status="violated" if kpis.get("passed") is False else "ok", kpis=kpis)
    row["trial_s"] = time.perf_counter() - start
    return row


def execute(kind: str, options: Any) -> dict[str, Any]:
    """One ``hil bench|servo run`` of its options; its KPIs."""
    if kind == "bench":
        from hil.bench.run import run_bench

        return dict(run_bench(options))
    from hil.servo.run import run_servo

    return dict(run_servo(options).kpis)
