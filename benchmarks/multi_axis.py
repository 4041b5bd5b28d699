"""Several axes on one SYNC: what a tick costs with 1, 2 and 3 axes on one bus,
lockstep through the CAN link (the masters' frames, one emulated CiA 402 node and plant per
axis), in one run:

1. the CAN cycle alone (every axis' RPDO, one SYNC, every axis' TPDO pair), next to one
   drive's master on its own link [baseline];
2. whole runs, fully recorded, PID on a 2 deg 1 Hz sine: ``hil servo run`` (one axis)
   [baseline] and ``hil servo run --axes`` with 2 and 3 axes, per tick.

Each figure is the quickest of ``--repeat`` alternated batches (this shared machine has slow
minutes: the quickest batch is the one it ran undisturbed). The target is that
each axis past the first costs at most 40 % of the first. Runs are at 2 kHz: the servo
controllers are designed for T = 500 us. ``--quick``: one batch of 200 cycles and runs of
0.1 s (a few seconds; figures not worth quoting).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from benchkit import add_quick, fill_defaults

from hil.core.run import run_experiment
from hil.drivers.canopen import CanDriveMaster, CanLink, DriveMasterConfig
from hil.drivers.canopen.axes import AxisBus, AxisGroup
from hil.emulators.drive.runners import LockstepDrive
from hil.servo.rig import open_drive
from hil.servo.run import ServoExperiment, ServoRunOptions


def group_cycle_us(axes: int, cycles: int) -> float:
    """One cycle of ``axes`` drives on one bus [us]."""
    ids = list(range(1, axes + 1))
    emulator = LockstepDrive(node_ids=ids)
    bus = AxisBus(CanLink(emulator.master_bus), ids)
    group = AxisGroup(bus, [CanDriveMaster(bus.node_link(n), DriveMasterConfig(node_id=n),
                                           clock=emulator) for n in ids])
    group.start()
    currents = [10.0] * axes
    begin = time.perf_counter()
    for _ in range(cycles):
        group.send_currents(currents)
        group.receive()
    elapsed = time.perf_counter() - begin
    group.close()
    emulator.close()
    return 1e6 * elapsed / cycles


def single_cycle_us(cycles: int) -> float:
    """One drive's master on its own link, the way a run drives it [us]."""
    master = open_drive("emulated", None)
    master.start()
    begin = time.perf_counter()
    for _ in range(cycles):
        master.exchange(10.0)
    elapsed = time.perf_counter() - begin
    master.close()
    return 1e6 * elapsed / cycles


def run_tick_us(axes: int, seconds: float, tmp: Path) -> float:
    """A whole lockstep run, fully recorded, per tick [us]: one axis as ``hil servo run``
    runs it, several as ``--axes`` does."""
    named = ",".join(f"a{i}={i}" for i in range(1, axes + 1)) if axes > 1 else None
    options = ServoRunOptions(controller="pid", duration_s=seconds, out=str(tmp / "run.mcap"),
                              quiet=True, axes=named)
    kpis = run_experiment(ServoExperiment(options)).kpis
    return 1e6 * seconds / float(kpis["realtime_factor"]) / (seconds / 500e-6)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cycles", type=int,
                        help="cycles per batch (default 4000; 200 with --quick)")
    parser.add_argument("--repeat", type=int,
                        help="batches of each, alternated (default 5; 1 with --quick)")
    parser.add_argument("--seconds", type=float,
                        help="simulated time per run (default 2; 0.1 with --quick)")
    add_quick(parser)
    args = parser.parse_args()
    fill_defaults(args, {"cycles": (4000, 200), "repeat": (5, 1), "seconds": (2.0, 0.1)})
    if args.cycles < 1 or args.repeat < 1:
        parser.error("--cycles and --repeat must be >= 1")
    runs: dict[str, list[float]] = {"single": [], "1": [], "2": [], "3": [],
                                    "run1": [], "run2": [], "run3": []}
    with tempfile.TemporaryDirectory() as name:
        for i in range(args.repeat):
            print(f"batch {i + 1} of {args.repeat}...", file=sys.stderr)
            runs["single"].append(single_cycle_us(args.cycles))
            for axes in (1, 2, 3):
                runs[str(axes)].append(group_cycle_us(axes, args.cycles))
                runs[f"run{axes}"].append(run_tick_us(axes, args.seconds, Path(name)))
    median = {key: min(values) for key, values in runs.items()}
    print(f"lockstep cycle through the CAN link, quickest of {args.repeat} x {args.cycles}")
    print(f"   one drive, its own link [baseline]   {median['single']:7.1f} us")
    for axes in (1, 2, 3):
        print(f"   {axes} drive(s) on one AxisBus           {median[str(axes)]:7.1f} us "
              f"({median[str(axes)] / median['single']:.2f}x the baseline)")
    first = median["1"]
    extra = (median["3"] - first) / 2
    print(f"   each axis past the first: {extra:.1f} us = {100 * extra / first:.0f} % of the first")
    print(f"whole lockstep runs, fully recorded, PID, {args.seconds:g} s, per tick")
    print(f"   hil servo run (one axis) [baseline]   {median['run1']:7.1f} us")
    for axes in (2, 3):
        print(f"   hil servo run --axes, {axes} axes         {median[f'run{axes}']:7.1f} us "
              f"({median[f'run{axes}'] / median['run1']:.2f}x the baseline)")
    run_extra = (median["run3"] - median["run1"]) / 2
    share = 100 * run_extra / median["run1"]
    print(f"   each axis past the first: {run_extra:.1f} us = {share:.0f} % of the first")
    print("targets")
    print(f"   each extra axis <= 40 % of the first, whole run ({share:.0f} %): "
          f"{'met' if share <= 40 else 'MISSED'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
