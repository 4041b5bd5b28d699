"""One trial: the options of ``hil bench|servo run`` with the swept values laid over them, run
in lockstep into its own MCAP file. Runs in a Ray worker or in this process alike.

A trial on Ray records its session in its own process (``RecordingOptions.in_process``): every
core already runs a trial there, and a writer process per trial would take half of each
core's time from the trials (a sweep of 12 trials on 2 cores ran 1.1 times as fast as one
after another). A trial run one after another keeps its writer process, which then has a
core of its own. A trial in real time keeps it too (the recorder refuses in-process recording
there: the encoding would be the loop's)."""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

from hil.core.run import Experiment, run_experiment
from hil.core.verdict import run_status
from hil.errors import HilError
from hil.sweep.space import PARAM_PREFIX


@dataclass(frozen=True)
class TrialJob:
    """Everything a worker needs: the run kind, the run's flags (argparse dests, as ``hil
    bench|servo run`` would parse them), the swept values, the trial's session file and
    whether it is recorded in the trial's own process (a lockstep trial; see the module)."""

    kind: str
    flags: dict[str, Any]
    name: str
    params: dict[str, Any]
    mcap: str
    in_process: bool = False


def flags_of(base: Mapping[str, Any], params: Mapping[str, Any]) -> dict[str, Any]:
    """The run's flags with ``params`` laid over them (``param.NAME`` over ``--param``)."""
    flags = dict(base)
    controller_params = dict(flags.get("param", []))
    for key, value in params.items():
        if key.startswith(PARAM_PREFIX):
            controller_params[key[len(PARAM_PREFIX):]] = value
        else:
            flags[key] = value
    flags["param"] = list(controller_params.items())
    return flags


def experiment_of(job: TrialJob) -> Experiment:
    """The trial's run, made from its flags as the command line makes one."""
    flags = flags_of(job.flags, job.params) | {"out": job.mcap}
    if job.kind == "bench":
        from hil.bench.run import BenchExperiment, BenchRunOptions

        return BenchExperiment(recorded_in_process(BenchRunOptions.from_flags(flags), job))
    from hil.servo.run import ServoExperiment, ServoRunOptions

    return ServoExperiment(recorded_in_process(ServoRunOptions.from_flags(flags), job))


def recorded_in_process(options: Any, job: TrialJob) -> Any:
    """``options`` recorded in the trial's process when ``job`` asks for it and they allow
    it (lockstep); else as they are."""
    if not job.in_process or options.realtime:
        return options
    return replace(options, recording=replace(options.recording, in_process=True))


def run_trial(job: TrialJob) -> dict[str, Any]:
    """Run ``job``; its result row (status ``ok``, ``violated`` when a --limit does not hold,
    or ``failed`` with the error; ``run_status``, the run's own status). Never raises for a
    failing run."""
    start = time.perf_counter()
    row: dict[str, Any] = {"name": job.name, "params": job.params, "mcap": job.mcap}
    try:
        result = run_experiment(experiment_of(job))
    except HilError as exc:
        so_far = exc.result.kpis if exc.result is not None else {}
        row.update(status="failed", run_status=so_far.get("status") or run_status({}, exc),
                   error=str(exc), kpis={})
    except Exception as exc:  # a trial's bug must not stop the sweep: it is recorded
        row.update(status="failed", run_status="failed", error=f"{type(exc).__name__}: {exc}",
                   kpis={})
    else:
        row.update(status="violated" if result.passed is False else "ok",
                   run_status=result.kpis.get("status", ""), kpis=dict(result.kpis))
    row["trial_s"] = time.perf_counter() - start
    return row
