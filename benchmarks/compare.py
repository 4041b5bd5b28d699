"""Reading sessions: what ``hil compare``, ``hil report`` and ``hil export`` cost on 60 s servo
sessions, against the code before sessions were read column by column, in the same run; and
what a baseline and an HTML report of a servo session weigh.

1. A lockstep PID session of ``--report-s`` seconds (10 s: 20 000 ticks) is recorded. Printed:
   the session file, its baseline as ``hil_baseline`` keeps it (position and command at every
   tick, and at every 10th), and its ``hil report --html`` page (plotly.js inlined, each trace
   decimated to 5000 points).
2. Two lockstep sessions of ``--compare-s`` seconds (60 s) that differ in their gain are
   recorded. ``hil compare`` of the two on position and command, ``hil report --json`` of one
   and ``hil export`` of its ``/drive/feedback`` to CSV are run ``--repeats`` times each, with
   this code and with the code before (``git archive`` of the parent of the commit that
   brought the column-wise reading, or ``--baseline-code DIR``), alternated. Printed for each:
   the median wall and CPU seconds and the peak memory of after and before, after/before, and
   the goal (the project's: compare <= 1 s, report <= 0.6 s, export <= 1 s of wall time, on a
   quiet machine); then compare against report of this code (report reads one file once: the
   yardstick). Both codes run from compiled bytecode (a warm-up run of each, not counted).

``--quick``: 0.5 s sessions (the sized one is the first compared: both are PID at its default
gain), one repeat, no warm-up runs (each code compiles in the run it times), the code before
for ``hil compare`` only (seconds; figures not worth quoting).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchkit import (
    REPO,
    add_baseline_code,
    add_quick,
    baseline_code,
    code_before_adding,
    fill_defaults,
)

from hil.cli.main import main as main_cli
from hil.compare.baseline import write_baseline
from hil.core.html_report import write_session_html

SIGNALS = ["/drive/feedback:position_deg", "/drive/command:command_mA"]
#: the commit that brought the column-wise reading: the code before is its parent's
COLUMN_READER = "hil/core/recording/cdr_columns.py"
#: each command, and its goal [s of wall time]
COMMANDS = {
    "compare": (["compare", "a.mcap", "b.mcap", *[a for s in SIGNALS for a in ("--signal", s)],
                 "--json"], 1.0),
    "report": (["report", "a.mcap", "--json"], 0.6),
    "export": (["export", "a.mcap", "--topic", "/drive/feedback", "--out", "feedback.csv"], 1.0),
}


def record(session: Path, seconds: float, *params: str) -> None:
    """A lockstep PID session of ``seconds`` into ``session`` (``hil servo run`` in this
    process: what is timed reads it, not how it was recorded)."""
    with contextlib.redirect_stdout(io.StringIO()):  # its summary: not this benchmark's
        status = main_cli(["servo", "run", "--controller", "pid", *params, "--duration",
                           str(seconds), "--out", str(session), "--quiet"])
    if status:
        raise SystemExit(f"hil servo run exited {status}")


def environment(code: Path) -> dict[str, str]:
    """The children's: the checkout at ``code`` first on the path, bytecode written (each
    command's first run compiles; the runs counted load it)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    return {**env, "PYTHONPATH": str(code)}


def timed(args: list[str], cwd: Path, code: Path) -> tuple[float, float, float]:
    """Wall and CPU seconds and peak memory [MiB] of ``hil ARGS`` with the checkout at
    ``code`` (its exit status 0 or 1: a comparison that fails is still a comparison)."""
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "hil", *args], cwd=cwd, env=environment(code),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    assert proc.stderr is not None
    errors = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode not in (0, 1):
        raise SystemExit(f"hil {' '.join(args)} ({code}) exited {proc.returncode}: "
                         f"{errors.decode(errors='replace')}")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024


def sizes(folder: Path, seconds: float, name: str = "s") -> None:
    """The sizes of the ``name``.mcap session recorded for them (PID, its default gain)."""
    session = folder / f"{name}.mcap"
    record(session, seconds)
    every_tick = write_baseline(session, folder / "base.mcap", SIGNALS)
    tenth = write_baseline(session, folder / "base10.mcap", SIGNALS, every=10)
    page = write_session_html(str(session), str(folder / "s.html"))
    print(f"{seconds:g} s servo session: {os.path.getsize(session) / 1e6:.2f} MB")
    print(f"  baseline (position, command, every tick): {every_tick / 1e6:.3f} MB; "
          f"every 10th tick: {tenth / 1e6:.3f} MB")
    print(f"  HTML report: {page.bytes / 1e6:.2f} MB ({page.plots} plots, {page.points} "
          f"points, {len(page.decimated)} of {page.traces} traces decimated)")


def speed(folder: Path, seconds: float, repeats: int, before: Path | None, why: str,
          quick: bool = False) -> None:
    """The commands timed on a.mcap (recorded unless there) and b.mcap, this code and the code
    ``before``; ``quick``: no warm-up runs, the code before runs ``hil compare`` only."""
    for name, kp in (("a", 3.6111), ("b", 3.0)):
        if (folder / f"{name}.mcap").exists():
            continue
        record(folder / f"{name}.mcap", seconds, "--param", f"kp={kp}")
    codes = {"after": REPO, **({"before": before} if before is not None else {})}
    for code in () if quick else codes.values():  # compiles each code's modules, not counted
        for args, _ in COMMANDS.values():
            timed(args, folder, code)
    runs: dict[tuple[str, str], list[tuple[float, float, float]]] = {}
    for _ in range(repeats):
        for name, (args, _) in COMMANDS.items():
            for side, code in codes.items():
                if side == "after" or name == "compare" or not quick:
                    runs.setdefault((name, side), []).append(timed(args, folder, code))
    median = {key: tuple(statistics.median(run[k] for run in v) for k in range(3))
              for key, v in runs.items()}
    print(f"two {seconds:g} s sessions ({repeats} alternated runs each, medians; before: "
          f"{why})")
    print(f"  {'':<12}{'wall s':>8}{'before':>8}{'ratio':>7}   {'cpu s':>6}{'before':>8}"
          f"{'ratio':>7}   {'peak MiB':>8}{'before':>8}   goal (wall)")
    for name, (_, goal) in COMMANDS.items():
        wall, cpu, peak = median[(name, "after")]
        line = f"  hil {name:<8}{wall:8.2f}"
        if (name, "before") in median:
            old_wall, old_cpu, old_peak = median[(name, "before")]
            line += (f"{old_wall:8.2f}{wall / old_wall:6.2f}x   {cpu:6.2f}{old_cpu:8.2f}"
                     f"{cpu / old_cpu:6.2f}x   {peak:8.0f}{old_peak:8.0f}")
        else:
            line += f"{'-':>8}{'-':>7}   {cpu:6.2f}{'-':>8}{'-':>7}   {peak:8.0f}{'-':>8}"
        print(f"{line}   <= {goal:g} s: {'met' if wall <= goal else 'not met'}")
    wall_ratio = median[("compare", "after")][0] / median[("report", "after")][0]
    cpu_ratio = median[("compare", "after")][1] / median[("report", "after")][1]
    print(f"  compare / report (this code): wall {wall_ratio:.2f}x, cpu {cpu_ratio:.2f}x")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--report-s", type=float, help="the sized session [s] (10)")
    parser.add_argument("--compare-s", type=float, help="the compared sessions [s] (60)")
    parser.add_argument("--repeats", type=int, help="runs of each command (5)")
    add_baseline_code(parser, f"the parent of the commit that added {COLUMN_READER}")
    add_quick(parser)
    args = parser.parse_args()
    fill_defaults(args, {"report_s": (10.0, 0.5), "compare_s": (60.0, 0.5),
                         "repeats": (5, 1)})
    with tempfile.TemporaryDirectory(prefix="hil-bench-compare-") as folder:
        before, why = baseline_code(args.baseline_code, Path(folder),
                                    lambda into: code_before_adding(COLUMN_READER, into))
        # --quick: the sized session is the first compared one (PID, default gain) if as long
        reuse = args.quick and args.report_s == args.compare_s
        sizes(Path(folder), args.report_s, "a" if reuse else "s")
        speed(Path(folder), args.compare_s, args.repeats, before, why, quick=args.quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
