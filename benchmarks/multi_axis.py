"""Several axes on one SYNC (issue 29), the driver's part: what a cycle costs with 1, 2 and 3
drives on one bus, lockstep through the CAN link (the masters' frames, one emulated CiA 402
node and plant per axis), next to one drive's master on its own link [baseline], in one run.

Each cycle sends every axis' RPDO, one SYNC, and reads every axis' TPDO pair. The figure is
the quickest of ``--repeat`` alternated batches (this shared machine has slow minutes: the
quickest batch is the one it ran undisturbed); the target (issue 29) is that each axis past
the first costs at most 40 % of the first. No recording and no controller here: ``hil servo
run`` drives one axis so far.
"""

from __future__ import annotations

import argparse
import sys
import time

from drivers.canopen import CanDriveMaster, CanLink, DriveMasterConfig
from drivers.canopen.axes import AxisBus, AxisGroup
from emulators.drive.runners import LockstepDrive
from hil.servo.rig import open_drive


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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cycles", type=int, default=4000, help="cycles per batch")
    parser.add_argument("--repeat", type=int, default=5, help="batches of each, alternated")
    args = parser.parse_args()
    if args.cycles < 1 or args.repeat < 1:
        parser.error("--cycles and --repeat must be >= 1")
    runs: dict[str, list[float]] = {"single": [], "1": [], "2": [], "3": []}
    for _ in range(args.repeat):
        runs["single"].append(single_cycle_us(args.cycles))
        for axes in (1, 2, 3):
            runs[str(axes)].append(group_cycle_us(axes, args.cycles))
    median = {key: min(values) for key, values in runs.items()}
    print(f"lockstep cycle through the CAN link, quickest of {args.repeat} x {args.cycles}")
    print(f"   one drive, its own link [baseline]   {median['single']:7.1f} us")
    for axes in (1, 2, 3):
        print(f"   {axes} drive(s) on one AxisBus           {median[str(axes)]:7.1f} us "
              f"({median[str(axes)] / median['single']:.2f}x the baseline)")
    first = median["1"]
    extra = (median["3"] - first) / 2
    print(f"each axis past the first: {extra:.1f} us = {100 * extra / first:.0f} % of the first")
    print("targets")
    print(f"   each extra axis <= 40 % of the first ({100 * extra / first:.0f} %): "
          f"{'met' if extra <= 0.4 * first else 'MISSED'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
