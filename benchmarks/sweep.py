"""Sweep benchmark: a 12-trial lockstep servo sweep on a local Ray against the same trials one
after another, measured in the same run.

The trials: MPC (FOH and ZOH) x 6 current limits, 20 s of a 1 Hz sine in lockstep each,
recorded to MCAP, as ``hil sweep servo`` runs them. Each repeat, in turn:

1. serial, as ``hil sweep --serial`` runs them: one after another in this process, each
   with its writer process (which has the other core to itself) [baseline];
2. on a local Ray of one worker per core, as ``hil sweep`` runs them: each trial recorded
   in its worker's own process (no writer process: every core runs a trial), from
   submission to the last result;
3. serial, recorded in-process like the Ray trials [the same work one after another].

Before the first repeat: one warm-up trial here and one on each Ray worker (neither side pays
its imports in the figures; a worker's first trial imports hil, about 2 s of CPU), and Ray's
start-up (timed apart: ``hil sweep`` pays it once per sweep, and its workers' imports too).
The goal is (2) at least 1.7x as fast as (1) on 2 cores; (2) against (3) is how the same
trials scale. Each ratio is the median of
the repeats' own ratios (pairs measured minutes apart on a shared machine). Also printed:
how many trials Ray kept in flight, whether every trial's KPIs match across the three, and
the load average: other processes on the cores slow the parallel run most.

``--quick``: 2 trials of 0.05 s each way in sequence, no Ray (its start-up alone takes 7-20 s
on a shared machine; the sweep's Ray path is tests/sweep/test_sweep_ray.py's): what ``make
test`` runs so that the script cannot rot, figures not worth quoting.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchkit import add_quick, fill_defaults

from hil.cli.servo import add_run_arguments
from hil.sweep.engine import Engine, import_ray, start_ray
from hil.sweep.space import expand
from hil.sweep.trial import TrialJob, run_trial

TARGET_SPEEDUP = 1.7
# 1200 and 1500 mA are above drive.toml's 1000 mA limit: a sweep over them says so
RUN = ["--controller", "mpc", "--reference", "sine:amplitude=2,frequency=1",
       "--allow-higher-current"]
GRID = {"umax": [600.0, 800.0, 900.0, 1000.0, 1200.0, 1500.0], "ert": ["zoh", "foh"]}
QUICK_GRID = {"umax": [800.0, 1500.0], "ert": ["foh"]}


def jobs_in(out: Path, seconds: float, quick: bool = False) -> list[TrialJob]:
    """The trials as ``hil sweep --serial`` makes them (each with its writer process)."""
    parser = argparse.ArgumentParser()
    add_run_arguments(parser)
    base = vars(parser.parse_args([*RUN, "--duration", f"{seconds:g}"]))
    return [TrialJob("servo", base, t.name, t.params, str(out / f"{t.name}.mcap"))
            for t in expand(QUICK_GRID if quick else GRID)]


def in_process(jobs: list[TrialJob]) -> list[TrialJob]:
    """The same trials as ``hil sweep`` makes them for Ray (recorded in their process)."""
    return [replace(job, in_process=True) for job in jobs]


def sweep_s(engine: Engine, jobs: list[TrialJob], cpu: dict[str, list[float]] | None = None
            ) -> tuple[float, list[dict[str, Any]]]:
    """Wall time of ``jobs`` on ``engine`` and their rows; every trial must pass. ``cpu``:
    where this process's CPU seconds per trial go (``self``; ``children``: the writer
    processes), for a sweep run in this process."""
    rows: list[dict[str, Any]] = []
    before = [resource.getrusage(who) for who in (resource.RUSAGE_SELF,
                                                  resource.RUSAGE_CHILDREN)]
    start = time.perf_counter()
    engine.run(run_trial, jobs, rows.append)
    wall = time.perf_counter() - start
    if cpu is not None:
        for key, who, was in zip(("self", "children"), (resource.RUSAGE_SELF,
                                                        resource.RUSAGE_CHILDREN), before,
                                 strict=True):
            now = resource.getrusage(who)
            used = now.ru_utime + now.ru_stime - was.ru_utime - was.ru_stime
            cpu.setdefault(key, []).append(used / len(jobs))
    failed = [row for row in rows if row["status"] != "ok"]
    assert not failed, failed
    return wall, rows


def kpis_of(rows: list[dict[str, Any]]) -> dict[str, float]:
    return {row["name"]: row["kpis"]["rms_error_deg"] for row in rows}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float,
                        help="lockstep seconds per trial (default 20; 0.05 with --quick)")
    parser.add_argument("--repeat", type=int,
                        help="repeats of the three sweeps, in turn (default 2; 1 with --quick)")
    add_quick(parser)
    args = parser.parse_args()
    fill_defaults(args, {"seconds": (20.0, 0.05), "repeat": (2, 1)})
    if args.seconds <= 0 or args.repeat < 1:
        parser.error("--seconds must be > 0 and --repeat >= 1")
    workers = os.cpu_count() or 1
    load_before = os.getloadavg()[0]
    serial = Engine(serial=True)
    with tempfile.TemporaryDirectory() as tmp:
        jobs = jobs_in(Path(tmp), args.seconds, args.quick)
        run_trial(jobs[0])   # warm-up: the baselines pay no imports
        if args.quick:
            process_s, _ = sweep_s(serial, jobs)
            inline_s, _ = sweep_s(serial, in_process(jobs))
            print(f"sweep: {len(jobs)} servo trials (MPC, {args.seconds:g} s lockstep each)\n"
                  f"  in sequence, writer processes  {process_s:7.2f} s\n"
                  f"  in sequence, in-process        {inline_s:7.2f} s\n"
                  "  on local Ray: skipped (--quick)")
            return 0
        ray = import_ray()
        startup = time.perf_counter()
        start_ray(ray, workers, None)
        ray.get(ray.remote(lambda: None).remote())
        startup = time.perf_counter() - startup
        warm_up = ray.remote(num_cpus=1)(run_trial)   # one at a time on each worker
        quick = in_process(jobs_in(Path(tmp), 0.05, quick=True))[0]
        warm = ray.get([warm_up.remote(replace(quick, mcap=f"{quick.mcap}.{i}"))
                        for i in range(workers)])
        assert all(row["status"] == "ok" for row in warm), warm
        on_ray = Engine(workers=workers)
        figures: dict[str, list[float]] = {"serial": [], "ray": [], "inline": []}
        busy: list[float] = []
        with_writer: dict[str, list[float]] = {}
        inline_cpu: dict[str, list[float]] = {}
        same = True
        for i in range(args.repeat):
            print(f"repeat {i + 1} of {args.repeat}...", file=sys.stderr)
            wall, rows = sweep_s(serial, jobs, with_writer)
            figures["serial"].append(wall)
            wall, ray_rows = sweep_s(on_ray, in_process(jobs))
            figures["ray"].append(wall)
            busy.append(sum(r["trial_s"] for r in ray_rows) / wall)
            wall, inline_rows = sweep_s(serial, in_process(jobs), inline_cpu)
            figures["inline"].append(wall)
            same = same and kpis_of(rows) == kpis_of(ray_rows) == kpis_of(inline_rows)
        ray.shutdown()

    def ratio(baseline: str) -> float:
        return statistics.median(b / r for b, r in zip(figures[baseline], figures["ray"],
                                                       strict=True))

    n = len(jobs)
    speedup = ratio("serial")
    print(f"sweep: {n} servo trials (MPC, {args.seconds:g} s lockstep each, recorded), "
          f"{workers} core(s), median of {args.repeat} repeat(s)")
    print(f"  hil sweep --serial (a writer process each) [baseline] "
          f"{statistics.median(figures['serial']):7.2f} s")
    print(f"  the same, recorded in-process like the Ray trials      "
          f"{statistics.median(figures['inline']):7.2f} s")
    print(f"  local Ray start-up (once per sweep)                    {startup:7.2f} s")
    print(f"  hil sweep on local Ray, {workers} workers                   "
          f"{statistics.median(figures['ray']):7.2f} s")
    print(f"  trials in flight on Ray (sum of trial times / wall): "
          f"{statistics.median(busy):.2f} of {workers}")
    loop_s, writer_s = min(with_writer["self"]), min(with_writer["children"])
    inline_s = min(inline_cpu["self"])
    print(f"  CPU per trial: hil sweep --serial {loop_s:.2f} s in the loop's process and "
          f"{writer_s:.2f} s in its writer process beside it; in-process {inline_s:.2f} s")
    print(f"  what the CPU allows on {workers} idle cores (a model: the serial run as fast as "
          f"its loop, Ray's trials side by side): {workers * loop_s / inline_s:.2f}x")
    print(f"  KPIs identical in the three: {same}")
    print(f"  load average before / after: {load_before:.1f} / {os.getloadavg()[0]:.1f} "
          f"(other processes on the {workers} cores slow the parallel run most)")
    print("targets")
    print(f"  Ray against hil sweep --serial: {speedup:.2f}x (target >= {TARGET_SPEEDUP}x: "
          f"{'met' if speedup >= TARGET_SPEEDUP else 'MISSED'})")
    print(f"  Ray against the same trials in-process one after another: "
          f"{ratio('inline'):.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
