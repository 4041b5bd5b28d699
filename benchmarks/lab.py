"""What ``--place`` adds to a run: a real labgrid coordinator and exporter on 127.0.0.1
publishing hil's bench emulator as a HilBench resource of the place ``bench``.

1. In this process: :func:`hil.lab.place.hold_place` entered (connect to the coordinator,
   acquire the place, read its resources) and left (release, disconnect), p50 and p90.
2. End to end: ``hil bench run --controller bc --cycles 1`` as a process, ``--bench URL``
   against ``--place bench``, alternated; the median of each and their difference (which adds
   labgrid's import, the connection, acquire and release to the run);
3. what importing labgrid alone adds to a process (``import hil.lab.place``).

The machine is shared: run it alone when the figures matter. ``--quick``: 2 holds, 1 run of
each, the runs 0.5 s of session time instead of a 28 s machine cycle (seconds; figures not
worth quoting).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from benchkit import add_quick, fill_defaults

from hil.emulator_process import start_bench_emulator
from hil.lab.local import BIN, local_lab
from hil.lab.place import hold_place

EXPORTER_YAML = "bench-1:\n  HilBench:\n    url: {url}\n"


def lab_client(address: str, *args: str) -> None:
    subprocess.run([str(BIN / "labgrid-client"), "-x", address, *args], check=True,
                   capture_output=True, timeout=120)


def holds(address: str, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Seconds to enter and to leave ``hold_place`` (acquire, release), ``count`` times."""
    enter, leave = np.empty(count), np.empty(count)
    for k in range(count):
        t0 = time.perf_counter()
        with hold_place("bench", address):
            t1 = time.perf_counter()
        enter[k], leave[k] = t1 - t0, time.perf_counter() - t1
    return enter, leave


def runs(address: str, url: str, folder: Path, count: int, length: list[str]
         ) -> tuple[np.ndarray, np.ndarray]:
    """Seconds of ``hil bench run LENGTH`` processes, plain and on the place, alternated."""
    plain, placed = np.empty(count), np.empty(count)
    base = [sys.executable, "-m", "hil", "bench", "run", "--controller", "bc", *length,
            "--quiet", "--out", str(folder / "b.mcap")]
    env = {k: v for k, v in os.environ.items() if k != "LG_COORDINATOR"}
    for k in range(count):
        for times, extra in ((plain, ["--bench", url]),
                             (placed, ["--place", "bench", "--coordinator", address])):
            t0 = time.perf_counter()
            subprocess.run([*base, *extra], cwd=folder, env=env, check=True,
                           capture_output=True, timeout=600)
            times[k] = time.perf_counter() - t0
    return plain, placed


def imports(count: int) -> tuple[np.ndarray, np.ndarray]:
    """Seconds of a process that imports hil's command line, without and with labgrid."""
    bare, lab = np.empty(count), np.empty(count)
    for k in range(count):
        for times, module in ((bare, "hil.cli.bench"), (lab, "hil.lab.place")):
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-c", f"import {module}"], check=True, timeout=120)
            times[k] = time.perf_counter() - t0
    return bare, lab


def ms(values: np.ndarray) -> str:
    p50, p90 = np.percentile(values * 1e3, [50, 90])
    return f"p50 {p50:7.1f} ms  p90 {p90:7.1f} ms"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--holds", type=int, help="in-process acquire/release (default 50)")
    parser.add_argument("--runs", type=int, help="runs of each kind (default 10)")
    add_quick(parser)
    args = parser.parse_args()
    fill_defaults(args, {"holds": (50, 2), "runs": (10, 1)})
    length = ["--duration", "0.5"] if args.quick else ["--cycles", "1"]
    with start_bench_emulator() as bench, tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        with local_lab(folder / "lab", EXPORTER_YAML.format(url=bench.url),
                       [("bench-1", "HilBench")]) as address:
            lab_client(address, "-p", "bench", "create")
            lab_client(address, "-p", "bench", "add-match", "hil-lab/bench-1/HilBench")
            enter, leave = holds(address, args.holds)
            print(f"hold_place, {args.holds} times (in this process)")
            print(f"  connect + acquire  {ms(enter)}")
            print(f"  release + close    {ms(leave)}")
            plain, placed = runs(address, bench.url, folder, args.runs, length)
    print(f"hil bench run --controller bc {' '.join(length)}, {args.runs} processes each")
    print(f"  --bench URL        {ms(plain)}")
    print(f"  --place bench      {ms(placed)}")
    print(f"  --place adds       {(np.median(placed) - np.median(plain)) * 1e3:7.1f} ms "
          "(difference of the medians)")
    bare, lab = imports(args.runs)
    print(f"importing labgrid (hil.lab.place), {args.runs} processes")
    print(f"  adds               {(np.median(lab) - np.median(bare)) * 1e3:7.1f} ms "
          "(difference of the medians)")


if __name__ == "__main__":
    main()
