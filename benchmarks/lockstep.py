"""The lockstep tick: how fast a servo session runs through the CAN link, and where
each tick's time goes.

1. Lockstep servo sessions through the CAN link (the master's frames, the emulated CiA 402
   node's object dictionary and plant, in-process), every topic recorded: MPC FOH
   H_t = H_u = 8, H_p = 50, and a controller that costs nothing (0 mA); and the same over the
   wire: the emulator in a process of its own (``hil emulate drive``), over socketcand on
   loopback, on the master's SYNC time. The factor is simulated time over the time the loop
   ticked (the writer's start and the safe stop are not the loop's pace); the median of
   ``--repeat`` alternated runs, and the wire's over the process's, run by run.
2. The tick broken down from the session's own timing topic (mean per tick, so that the
   columns add up): CAN receive (``read``: over the wire, mostly the wait for the drive's
   answer), the controller (``compute``), CAN send (``write``: in process, the emulated node
   and plant too), the tick's recording and KPIs (``record``), and the rest: the loop, the
   hand-over to the writer, and whatever held the process up outside the phases.
3. The recorder's cost on the loop per tick: the three servo messages of a tick queued and
   handed to a real writer process, as packed rows (what a run does) against the same
   messages as dicts (as hil recorded them before), in the same run. Each repeat times
   ``RECORDERS`` recorders of each form, alternated, and keeps each form's quickest: one
   recorder's ticks cost the same all along, but from one recorder to the next the cost
   differs up to twice (4.7 against 8.5 us measured, as the writer process lands: its core
   shared with the loop or not).
4. One CAN cycle alone (RPDO + SYNC, TPDO pair back) and the emulated node's share of it.

Targets: MPC >= 10x real time, 0 mA >= 25x, over the wire at least half the in-process speed
(MPC and 0 mA, the same run), recorder <= 5 us per tick. The machine is shared: figures drift
up to 2x between minutes, and a loaded one (its load average is printed) leaves the two
processes no core of their own, which is what the wire's speed needs; use ``--repeat 3`` or
more on a quiet machine. ``--quick``:
one run of each kind, 0.1 s each, both wire runs on one emulator process, 200 recorder ticks
and 100 CAN cycles (seconds in all; figures not worth quoting).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from benchkit import add_quick

from hil.api import start_drive_emulator
from hil.core.recording.reader import read_session
from hil.core.recording.recorder import Recorder
from hil.servo.rig import open_drive
from hil.servo.run import ServoRunOptions, run_servo
from hil.servo.topics import COMMAND_SCHEMA, FEEDBACK_SCHEMA, PREDICTION_SCHEMA

PERIOD_S = 500e-6
PHASES = ("read", "compute", "write", "record")
WIRE_SHARE_MIN = 0.5  # over the wire: at least this share of the in-process speed
RECORDERS = 4  # recorders of each form a repeat times (the quickest counts), its ticks split

class ZeroCurrent:
    """A controller that costs nothing (0 mA every tick): the floor of a lockstep tick."""

    def __init__(self, reference: Any, params: Any) -> None:
        pass

    def step(self, position_deg: float, t_s: float) -> float:
        return 0.0


def session(tmp: Path, seconds: float, controller: Any, wire: bool = False,
            emulator_url: str | None = None) -> dict[str, Any]:
    """One lockstep run, fully recorded: its factor and the tick's phases (p50, us). With
    ``wire``: the emulator in a process of its own (started for the run, or the one at
    ``emulator_url``), over socketcand on loopback, on the master's SYNC time (the emulator in
    this process otherwise)."""
    out = tmp / "lockstep.mcap"
    with contextlib.ExitStack() as stack:
        drive = None
        if wire:
            drive = emulator_url or stack.enter_context(start_drive_emulator()).url
        result = run_servo(ServoRunOptions(controller=controller, ert="foh", ht=8, hu=8,
                                           duration_s=seconds, realtime=False, out=str(out),
                                           drive=drive))
    ticks = result.kpis["ticks"]
    factor = float(result.kpis["realtime_factor"])
    timing = [m for _, m in read_session(out).topic("/loop/servo/timing")]
    phases = {phase: float(np.mean(np.concatenate(
        [np.asarray(m[f"{phase}_us"], float) for m in timing]))) for phase in PHASES}
    per_tick_us = 1e6 * ticks * PERIOD_S / factor / ticks
    phases["loop"] = per_tick_us - sum(phases.values())
    out.unlink()
    return {"factor": factor, "per_tick_us": per_tick_us, "phases": phases}


def recorder_cost(path: Path, ticks: int, rows: bool) -> float:
    """Per tick [us]: a tick's three servo messages queued and handed over to the writer,
    the loop's side only (the hand-over never waits: the writer's own pace is not the
    loop's cost as long as it keeps up, and the backlog holds the whole run)."""
    rec = Recorder(path, max_backlog_bytes=1 << 30)
    commands = rec.topic("/drive/command", COMMAND_SCHEMA, high_rate=True)
    feedbacks = rec.topic("/drive/feedback", FEEDBACK_SCHEMA, high_rate=True)
    predictions = rec.topic("/mpc/prediction", PREDICTION_SCHEMA, high_rate=True)
    rec.wait_ready()
    u_pred, y_pred = np.linspace(-5, 5, 50), np.linspace(0, 2, 50)
    begin = time.perf_counter()
    for k in range(ticks):
        t_ns, t_s, x = k * 500_000, k * PERIOD_S, k * 1e-3
        if rows:
            feedbacks.log(t_ns, (x, 2.0 * x, 3.0, 4.0, 0x1637, k, True, 33.0))
            commands.log(t_ns, (t_s, x, 0.01 * x, 4.0, None, 20.0, "unconstrained"))
            predictions.log(t_ns, (t_s, u_pred[:8].tolist(), y_pred.tolist()))
        else:
            feedbacks.log(t_ns, {"position_deg": x, "velocity_deg_s": 2.0 * x,
                                 "current_mA": 3.0, "command_mA": 4.0, "statusword": 0x1637,
                                 "cycle": k, "fresh": True, "rtt_us": 33.0})
            commands.log(t_ns, {"t_s": t_s, "reference_deg": x, "error_deg": 0.01 * x,
                                "command_mA": 4.0, "compute_us": 20.0,
                                "path": "unconstrained"})
            predictions.log(t_ns, {"t_s": t_s, "u_mA": u_pred[:8], "y_deg": y_pred})
        rec.flush_if_due()
    elapsed = time.perf_counter() - begin
    stats = rec.close()
    assert not stats.messages_dropped and stats.messages_written == 3 * ticks, stats
    return 1e6 * elapsed / ticks


def can_cycle(cycles: int) -> tuple[float, float]:
    """One exchange through the master and the lockstep node [us], and the node's part."""
    master = open_drive("emulated", None)
    master.start()
    emulator = master.emulator
    pump, spent = emulator.pump, [0]

    def timed_pump() -> None:
        begin = time.perf_counter_ns()
        pump()
        spent[0] += time.perf_counter_ns() - begin

    emulator.master_bus._on_send = timed_pump
    best = (float("inf"), 0.0)
    for _ in range(10):
        spent[0] = 0
        begin = time.perf_counter_ns()
        for _ in range(cycles // 10):
            master.exchange(10.0)
        total = (time.perf_counter_ns() - begin) / (cycles // 10) / 1e3
        best = min(best, (total, spent[0] / (cycles // 10) / 1e3))
    master.close()
    return best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float,
                        help="simulated time per run [s] (default 5; 0.1 with --quick)")
    parser.add_argument("--repeat", type=int,
                        help="runs of each kind, alternated (default 3; 1 with --quick)")
    add_quick(parser)
    args = parser.parse_args()
    args.seconds = args.seconds if args.seconds is not None else (0.1 if args.quick else 5.0)
    args.repeat = args.repeat if args.repeat is not None else (1 if args.quick else 3)
    sizes = 200 if args.quick else 20_000  # recorder ticks; CAN cycles (100 quick)
    if args.repeat < 1 or not args.seconds > 0:
        parser.error("--repeat must be >= 1 and --seconds > 0")
    runs: dict[str, list[dict[str, Any]]] = {"mpc": [], "zero": [], "mpc-wire": [],
                                             "zero-wire": []}
    costs: dict[str, list[float]] = {"rows": [], "dicts": []}
    load = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as name, contextlib.ExitStack() as stack:
        tmp = Path(name)
        # --quick: one emulator process for both wire runs (each run starts its own otherwise)
        shared = stack.enter_context(start_drive_emulator()).url if args.quick else None
        for i in range(args.repeat):
            print(f"run {i + 1} of {args.repeat}...", file=sys.stderr)
            runs["mpc"].append(session(tmp, args.seconds, "mpc"))
            runs["zero"].append(session(tmp, args.seconds, ZeroCurrent))
            runs["mpc-wire"].append(session(tmp, args.seconds, "mpc", True, shared))
            runs["zero-wire"].append(session(tmp, args.seconds, ZeroCurrent, True, shared))
            timed: dict[str, list[float]] = {"dicts": [], "rows": []}
            for j in range(RECORDERS):
                for form in timed:
                    timed[form].append(recorder_cost(tmp / f"recorder-{form}-{i}-{j}.mcap",
                                                     sizes // RECORDERS, rows=form == "rows"))
            for form, got in timed.items():
                costs[form].append(min(got))
    cycle_us, node_us = can_cycle(sizes // 2 if args.quick else sizes)
    load.append(os.getloadavg()[0])

    print(f"machine load average (1 min): {load[0]:.2f} before, {load[1]:.2f} after, on "
          f"{os.cpu_count()} CPUs (the wire's figures are worth quoting near 0)")
    print(f"lockstep servo through the CAN link, {args.seconds:g} s, fully recorded "
          f"(median of {args.repeat}; the phases: mean us per tick)")
    print(f"{'controller':<28}{'x real time':>12}{'us/tick':>9}" +
          "".join(f"{p:>9}" for p in (*PHASES, "rest")))
    medians = {}
    for kind, label in (("mpc", "MPC FOH Ht=Hu=8 Hp=50"), ("zero", "0 mA (costs nothing)"),
                        ("mpc-wire", "MPC, over socketcand"),
                        ("zero-wire", "0 mA, over socketcand")):
        run = sorted(runs[kind], key=lambda r: r["factor"])[(args.repeat - 1) // 2]
        medians[kind] = run["factor"]
        print(f"{label:<28}{run['factor']:>12.2f}{run['per_tick_us']:>9.1f}" +
              "".join(f"{run['phases'][p]:>9.1f}" for p in (*PHASES, "loop")))
    shares = {}
    for kind, label in (("mpc", "MPC"), ("zero", "0 mA")):
        pairs = [wire["factor"] / near["factor"] for near, wire in
                 zip(runs[kind], runs[kind + "-wire"], strict=True)]
        shares[kind] = medians[kind + "-wire"] / medians[kind]
        print(f"over the wire against in process, {label}: {medians[kind + '-wire']:.2f}x "
              f"against {medians[kind]:.2f}x real time = {shares[kind]:.2f} of the in-process "
              f"speed (run by run: {', '.join(f'{p:.2f}' for p in pairs)})")
    rows, dicts = statistics.median(costs["rows"]), statistics.median(costs["dicts"])
    print(f"recorder per tick (3 messages, handed to the writer process; the quickest of "
          f"{RECORDERS} recorders): rows {rows:.2f} us, dicts {dicts:.2f} us [baseline] "
          f"({dicts / rows:.1f}x)")
    print(f"one CAN cycle (master + emulated node + plant): {cycle_us:.1f} us, of which the "
          f"node {node_us:.1f} us")
    print("targets")
    for label, value, bar in (("MPC >= 10x", medians["mpc"], 10.0),
                              ("0 mA >= 25x", medians["zero"], 25.0)):
        print(f"   {label} ({value:.1f}x): {'met' if value >= bar else 'MISSED'}")
    for label, kind in (("MPC", "mpc"), ("0 mA", "zero")):
        print(f"   over the wire >= {WIRE_SHARE_MIN:g} of in process, {label} "
              f"({shares[kind]:.2f}): {'met' if shares[kind] >= WIRE_SHARE_MIN else 'MISSED'}")
    print(f"   recorder <= 5 us per tick ({rows:.2f} us): {'met' if rows <= 5 else 'MISSED'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
