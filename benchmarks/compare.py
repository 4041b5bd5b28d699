"""Regression against a baseline: what a baseline and an HTML report of a servo session weigh,
and what ``hil compare`` costs next to ``hil report`` on the same sessions, in the same run.

1. A lockstep PID session of ``--report-s`` seconds (10 s: 20 000 ticks) is recorded. Printed:
   the session file, its baseline as ``hil_baseline`` keeps it (position and command at every
   tick, and at every 10th), and its ``hil report --html`` page (plotly.js inlined, each trace
   decimated to 5000 points).
2. Two lockstep sessions of ``--compare-s`` seconds (60 s) that differ in their gain are
   recorded. ``hil compare`` of the two on position and command and ``hil report`` of one are
   run ``--repeats`` times each, alternated; printed: the median wall and CPU seconds of each
   and their ratio (``hil report`` reads the same file once: the yardstick).

``--quick``: 1 s and 2 s sessions, one repeat (seconds; figures not worth quoting).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchkit import add_quick, fill_defaults

from hil.compare.baseline import write_baseline
from hil.core.html_report import write_session_html

SIGNALS = ["/drive/feedback:position_deg", "/drive/command:command_mA"]


def hil(*args: str, cwd: Path) -> None:
    subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def timed(args: list[str], cwd: Path) -> tuple[float, float]:
    """Wall and CPU seconds of ``hil ARGS`` (its exit status 0 or 1: a comparison that fails
    is still a comparison)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd,
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode not in (0, 1):
        raise SystemExit(f"hil {' '.join(args)} exited {done.returncode}: {done.stderr}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def sizes(folder: Path, seconds: float) -> None:
    hil("servo", "run", "--controller", "pid", "--duration", str(seconds), "--out", "s.mcap",
        "--quiet", cwd=folder)
    session = folder / "s.mcap"
    every_tick = write_baseline(session, folder / "base.mcap", SIGNALS)
    tenth = write_baseline(session, folder / "base10.mcap", SIGNALS, every=10)
    page = write_session_html(str(session), str(folder / "s.html"))
    print(f"{seconds:g} s servo session: {os.path.getsize(session) / 1e6:.2f} MB")
    print(f"  baseline (position, command, every tick): {every_tick / 1e6:.3f} MB; "
          f"every 10th tick: {tenth / 1e6:.3f} MB")
    print(f"  HTML report: {page.bytes / 1e6:.2f} MB ({page.plots} plots, {page.points} "
          f"points, {len(page.decimated)} of {page.traces} traces decimated)")


def speed(folder: Path, seconds: float, repeats: int) -> None:
    for name, kp in (("a", 3.6111), ("b", 3.0)):
        hil("servo", "run", "--controller", "pid", "--param", f"kp={kp}", "--duration",
            str(seconds), "--out", f"{name}.mcap", "--quiet", cwd=folder)
    compare = ["compare", "a.mcap", "b.mcap", *[a for s in SIGNALS for a in ("--signal", s)],
               "--json"]
    report = ["report", "a.mcap", "--json"]
    runs: dict[str, list[tuple[float, float]]] = {"compare": [], "report": []}
    for _ in range(repeats):
        runs["compare"].append(timed(compare, folder))
        runs["report"].append(timed(report, folder))
    wall = {k: statistics.median(w for w, _ in v) for k, v in runs.items()}
    cpu = {k: statistics.median(c for _, c in v) for k, v in runs.items()}
    print(f"two {seconds:g} s sessions ({repeats} alternated runs each, medians):")
    for name in ("compare", "report"):
        print(f"  hil {name:<8} wall {wall[name]:6.2f} s  cpu {cpu[name]:6.2f} s")
    print(f"  compare / report: wall {wall['compare'] / wall['report']:.2f}x, "
          f"cpu {cpu['compare'] / cpu['report']:.2f}x")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--report-s", type=float, help="the sized session [s] (10)")
    parser.add_argument("--compare-s", type=float, help="the compared sessions [s] (60)")
    parser.add_argument("--repeats", type=int, help="runs of each command (5)")
    add_quick(parser)
    args = parser.parse_args()
    fill_defaults(args, {"report_s": (10.0, 1.0), "compare_s": (60.0, 2.0),
                         "repeats": (5, 1)})
    with tempfile.TemporaryDirectory(prefix="hil-bench-compare-") as folder:
        sizes(Path(folder), args.report_s)
        speed(Path(folder), args.compare_s, args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
