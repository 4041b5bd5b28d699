"""Several axes on one SYNC: what a tick costs with 1, 2 and 3 axes on one bus,
lockstep through the CAN link (the masters' frames, one emulated CiA 402 node and plant per
axis), in one run:

1. the CAN cycle alone (every axis' RPDO, one SYNC, every axis' TPDO pair), next to one
   drive's master on its own link [baseline]: CPU time of this thread per cycle;
2. whole runs, fully recorded, PID on a 2 deg 1 Hz sine: ``hil servo run`` (one axis)
   [baseline] and ``hil servo run --axes`` with 2 and 3 axes, per tick: the wall time the
   loop spent ticking (the run's ``realtime_factor``, the writer process working beside it
   on the other core) and this process's CPU time per tick (a run of ``--seconds`` less one
   of a quarter of it: the set-up and the file's finish cancel out; steadier than the wall
   time on a shared machine), of which the emulated drives' (``LockstepDrive.pump``: each
   node's frames, plant and answers, work real drives do themselves): what is left is hil's
   own work per tick, printed with its share too.

Each figure is the quickest of ``--repeat`` alternated batches (this shared machine has slow
minutes: the quickest batch is the one it ran undisturbed). The target is that each axis past
the first costs at most 40 % of the first, in whole runs (met when both figures are).
Runs are at 2 kHz: the servo
controllers are designed for T = 500 us. ``--quick``: one batch of 200 cycles and runs of
0.1 s (a few seconds; figures not worth quoting).
"""

from __future__ import annotations

import argparse
import os
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

TICK_S = 500e-6  # the runs' base period (master.cycle_period_us)


class DriveTime:
    """CPU seconds this thread spends in the emulated drives of the lockstep runs started
    while it is on (each :class:`LockstepDrive`'s ``pump``, timed)."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self._pump = LockstepDrive.pump

    def __enter__(self) -> DriveTime:
        pump = self._pump

        def timed(drive: LockstepDrive) -> None:
            begin = time.thread_time()
            try:
                pump(drive)
            finally:
                self.seconds += time.thread_time() - begin

        LockstepDrive.pump = timed  # type: ignore[method-assign]
        return self

    def __exit__(self, *_exc: object) -> None:
        LockstepDrive.pump = self._pump  # type: ignore[method-assign]


def group_cycle_us(axes: int, cycles: int) -> float:
    """One cycle of ``axes`` drives on one bus [us of CPU]."""
    ids = list(range(1, axes + 1))
    emulator = LockstepDrive(node_ids=ids)
    bus = AxisBus(CanLink(emulator.master_bus), ids)
    group = AxisGroup(bus, [CanDriveMaster(bus.node_link(n), DriveMasterConfig(node_id=n),
                                           clock=emulator) for n in ids])
    group.start()
    currents = [10.0] * axes
    begin = time.thread_time()
    for _ in range(cycles):
        group.send_currents(currents)
        group.receive()
    elapsed = time.thread_time() - begin
    group.close()
    emulator.close()
    return 1e6 * elapsed / cycles


def single_cycle_us(cycles: int) -> float:
    """One drive's master on its own link, the way a run drives it [us of CPU]."""
    master = open_drive("emulated", None)
    master.start()
    begin = time.thread_time()
    for _ in range(cycles):
        master.exchange(10.0)
    elapsed = time.thread_time() - begin
    master.close()
    return 1e6 * elapsed / cycles


def run(axes: int, seconds: float, tmp: Path) -> tuple[float, float, float]:
    """A whole lockstep run, fully recorded (one axis as ``hil servo run`` runs it, several as
    ``--axes`` does): the wall time the loop spent per tick [us], this process's CPU time for
    the whole run [s] and the emulated drives' part of it [s]."""
    named = ",".join(f"a{i}={i}" for i in range(1, axes + 1)) if axes > 1 else None
    options = ServoRunOptions(controller="pid", duration_s=seconds, out=str(tmp / "run.mcap"),
                              quiet=True, axes=named)
    with DriveTime() as drives:
        begin = time.process_time()
        kpis = run_experiment(ServoExperiment(options)).kpis
        cpu_s = time.process_time() - begin
    return 1e6 * TICK_S / float(kpis["realtime_factor"]), cpu_s, drives.seconds


def run_tick_us(axes: int, seconds: float, tmp: Path) -> tuple[float, float, float]:
    """Per tick of a whole run of ``axes``: wall [us] (the run of ``seconds``), CPU and the
    emulated drives' CPU [us] (that run's less a quarter as long one's, over the ticks
    between them)."""
    wall_us, long_cpu, long_drives = run(axes, seconds, tmp)
    _, short_cpu, short_drives = run(axes, seconds / 4, tmp)
    ticks = 0.75 * seconds / TICK_S
    return (wall_us, 1e6 * (long_cpu - short_cpu) / ticks,
            1e6 * (long_drives - short_drives) / ticks)


def share(first: float, third: float) -> float:
    """Each axis past the first, from one axis' and three axes' figures, in % of the first."""
    return 100 * (third - first) / 2 / first


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
    runs: dict[str, list[float]] = {key: [] for key in (
        "single", "1", "2", "3", "run1", "run2", "run3", "cpu1", "cpu2", "cpu3", "own1",
        "own2", "own3")}
    with tempfile.TemporaryDirectory() as name:
        for i in range(args.repeat):
            print(f"batch {i + 1} of {args.repeat}...", file=sys.stderr)
            runs["single"].append(single_cycle_us(args.cycles))
            for axes in (1, 2, 3):
                runs[str(axes)].append(group_cycle_us(axes, args.cycles))
                wall_us, cpu_us, drives_us = run_tick_us(axes, args.seconds, Path(name))
                runs[f"run{axes}"].append(wall_us)
                runs[f"cpu{axes}"].append(cpu_us)
                runs[f"own{axes}"].append(cpu_us - drives_us)
    best = {key: min(values) for key, values in runs.items()}
    print(f"lockstep cycle through the CAN link, CPU, quickest of {args.repeat} x {args.cycles}")
    print(f"   one drive, its own link [baseline]   {best['single']:7.1f} us")
    for axes in (1, 2, 3):
        print(f"   {axes} drive(s) on one AxisBus           {best[str(axes)]:7.1f} us "
              f"({best[str(axes)] / best['single']:.2f}x the baseline)")
    cycle_share = share(best["1"], best["3"])
    print(f"   each axis past the first: {(best['3'] - best['1']) / 2:.1f} us = "
          f"{cycle_share:.0f} % of the first")
    print(f"whole lockstep runs, fully recorded, PID, {args.seconds:g} s, per tick "
          "(wall while ticking; CPU of this process)")
    print(f"   hil servo run (one axis) [baseline]   {best['run1']:7.1f} us  "
          f"{best['cpu1']:7.1f} us CPU")
    for axes in (2, 3):
        print(f"   hil servo run --axes, {axes} axes         {best[f'run{axes}']:7.1f} us  "
              f"{best[f'cpu{axes}']:7.1f} us CPU ({best[f'run{axes}'] / best['run1']:.2f}x / "
              f"{best[f'cpu{axes}'] / best['cpu1']:.2f}x the baseline)")
    wall_share, cpu_share = share(best["run1"], best["run3"]), share(best["cpu1"], best["cpu3"])
    print(f"   each axis past the first: {(best['run3'] - best['run1']) / 2:.1f} us = "
          f"{wall_share:.0f} % of the first (CPU: {(best['cpu3'] - best['cpu1']) / 2:.1f} us "
          f"= {cpu_share:.0f} %)")
    own_share = share(best["own1"], best["own3"])
    print(f"   hil's own work, the emulated drives' CPU taken out: {best['own1']:.1f} us with "
          f"one axis, {best['own3']:.1f} us with 3; each axis past the first "
          f"{(best['own3'] - best['own1']) / 2:.1f} us = {own_share:.0f} % of the first")
    print(f"   load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} core(s)")
    print("targets")
    print(f"   each extra axis <= 40 % of the first, whole run ({wall_share:.0f} %; CPU "
          f"{cpu_share:.0f} %): {'met' if max(wall_share, cpu_share) <= 40 else 'MISSED'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
