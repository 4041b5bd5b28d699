"""Sweep benchmark: an 8-trial servo sweep on a local Ray against the same trials
one after another in this process, measured in the same run.

1. Sequential baseline: the 8 trials (MPC FOH/ZOH x 4 current limits, 3 s of a 1 Hz sine in
   lockstep each, recorded to MCAP) run in this process one after another, after one warm-up
   run so the baseline pays no imports (the strict baseline of the target); and the same in
   a fresh process with its imports, as a script looping over the trials pays them once.
2. Local Ray start-up: ``ray.init`` for the sweep (one worker per core, loopback, quiet) until
   a first empty task has come back.
3. The same 8 trials as Ray tasks on that Ray (workers start cold: each imports hil once),
   from submission to the last result. Target: >= 1.7x faster than (1) on 2 cores; the ratio
   with the start-up of (2) included is printed too.
4. Per-trial overhead: one trial as a Ray task on a warm worker (submit -> result) against
   the same trial in this process, median of 3.

Also printed: how many trials Ray kept in flight on average, and the load average, since on a
shared machine other processes take the cores the workers need.

The machine is shared: figures are noisy, run it alone when the numbers matter.

``--quick``: 2 trials of 0.05 s in sequence, in-process, and no Ray at all (its start-up alone
takes 7-20 s on a shared machine; the sweep's Ray path is tests/sweep/test_sweep_ray.py's):
what ``make test`` runs so that the script cannot rot, figures not worth quoting.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchkit import add_quick

from hil.cli.servo import add_run_arguments
from hil.sweep.engine import Engine, import_ray, start_ray
from hil.sweep.space import expand
from hil.sweep.trial import TrialJob, run_trial

TARGET_SPEEDUP = 1.7
# 1200 and 1500 mA are above drive.toml's 1000 mA limit: a sweep over them says so
RUN = ["--controller", "mpc", "--duration", "3", "--reference",
       "sine:amplitude=2,frequency=1", "--allow-higher-current"]
GRID = {"umax": [800.0, 1000.0, 1200.0, 1500.0], "ert": ["zoh", "foh"]}
QUICK_RUN = [*RUN[:2], "--duration", "0.05", *RUN[4:]]
QUICK_GRID = {"umax": [800.0, 1500.0], "ert": ["foh"]}

def jobs_in(out: Path, quick: bool = False) -> list[TrialJob]:
    parser = argparse.ArgumentParser()
    add_run_arguments(parser)
    base = vars(parser.parse_args(QUICK_RUN if quick else RUN))
    return [TrialJob("servo", base, t.name, t.params, str(out / f"{t.name}.mcap"))
            for t in expand(QUICK_GRID if quick else GRID)]


def timed(function, *args):  # type: ignore[no-untyped-def]
    start = time.perf_counter()
    result = function(*args)
    return time.perf_counter() - start, result


def sequential_cold(out: Path) -> float:
    """The 8 trials in sequence in a fresh process, its imports included (as a script that
    loops over the trials pays them, and as each Ray worker does)."""
    code = ("import sys, time; sys.path.insert(0, 'benchmarks'); import sweep; "
            "from hil.sweep.trial import run_trial; from pathlib import Path; "
            "t = time.perf_counter(); "
            f"rows = [run_trial(j) for j in sweep.jobs_in(Path({str(out)!r}))]; "
            "assert all(r['status'] == 'ok' for r in rows); print(time.perf_counter() - t)")
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True,
                          text=True, check=True)
    return float(done.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_quick(parser)
    args = parser.parse_args()
    workers = os.cpu_count() or 1
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        cold = None if args.quick else sequential_cold(out)
        jobs = jobs_in(out, args.quick)
        run_trial(jobs[0])   # warm-up: the baseline pays no imports
        sequential, rows = timed(lambda: [run_trial(j) for j in jobs])
        assert all(r["status"] == "ok" for r in rows), rows
        if args.quick:
            print(f"sweep: {len(jobs)} servo trials (MPC, {jobs[0].flags['duration']:g} s "
                  f"lockstep each)\n  in sequence, in-process      {sequential:7.2f} s  "
                  f"({sequential / len(jobs):.2f} s/trial)\n  on local Ray: skipped (--quick)")
            return 0

        ray = import_ray()
        startup, _ = timed(lambda: (start_ray(ray, workers, None),
                                    ray.get(ray.remote(lambda: None).remote())))
        ray_rows: list[dict] = []
        on_ray, _ = timed(Engine(workers=workers).run, run_trial, jobs, ray_rows.append)
        assert all(r["status"] == "ok" for r in ray_rows), ray_rows
        by_name = {r["name"]: r["kpis"] for r in rows}
        same = all(r["kpis"]["rms_error_deg"] == by_name[r["name"]]["rms_error_deg"]
                   for r in ray_rows)

        task = ray.remote(num_cpus=1, max_retries=0)(run_trial)
        overheads, local_times, remote_times = [], [], []
        for _ in range(1 if args.quick else 3):
            remote_s, _ = timed(lambda: ray.get(task.remote(jobs[1])))
            local_s, _ = timed(run_trial, jobs[1])
            remote_times.append(remote_s)
            local_times.append(local_s)
            overheads.append(remote_s - local_s)
        ray.shutdown()

    speedup = sequential / on_ray
    busy = sum(r["trial_s"] for r in ray_rows) / on_ray
    n = len(jobs)
    print(f"sweep: {n} servo trials (MPC, {jobs[0].flags['duration']:g} s lockstep each), "
          f"{workers} core(s)")
    print(f"  in sequence, in-process      {sequential:7.2f} s  ({sequential / n:.2f} s/trial, "
          "imports done before)")
    if cold is None:
        print("  in sequence, fresh process   skipped (--quick)")
    else:
        print(f"  in sequence, fresh process   {cold:7.2f} s  (its imports included, as each "
              "Ray worker pays them)")
    print(f"  local Ray start-up           {startup:7.2f} s")
    print(f"  on local Ray, {workers} workers      {on_ray:7.2f} s  -> {speedup:.2f}x "
          f"(target >= {TARGET_SPEEDUP}x: {'met' if speedup >= TARGET_SPEEDUP else 'MISSED'})")
    print(f"  with the start-up            {startup + on_ray:7.2f} s  -> "
          f"{sequential / (startup + on_ray):.2f}x")
    if cold is not None:
        print(f"  against the fresh process    {on_ray:7.2f} s  -> {cold / on_ray:.2f}x")
    print(f"  per-trial overhead (Ray task on a warm worker vs in-process, median of "
          f"{len(overheads)}): "
          f"{statistics.median(overheads) * 1e3:+.0f} ms "
          f"({statistics.median(remote_times):.2f} s vs {statistics.median(local_times):.2f} s)")
    print(f"  trials in flight on Ray (sum of trial times / wall): {busy:.2f} of {workers}")
    print(f"  KPIs identical to the in-process runs: {same}")
    print(f"  load average before / after: {load_before:.1f} / {os.getloadavg()[0]:.1f} "
          f"(other processes on the {workers} cores slow the parallel run most)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
