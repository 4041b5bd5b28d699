"""The real-time path, each suspect of a late or skipped tick against the bare loop, in one run.

Each repeat runs, one after the other, at 2 kHz with the loop thread hardened as a session's is:

1. ``bare`` - the bare loop as ``hil doctor`` runs it (no I/O): the baseline;
2. ``recorder`` - the loop recording what a servo tick records (its three messages, packed
   rows) through a session's writer process: the writer and the hand-over to it;
3. ``wire`` - the loop cycling the drive emulator in a process of its own over socketcand
   (RPDO + SYNC each tick, the TPDOs read the next), 0 mA, nothing recorded but the loop's
   timing: the emulator process's answer (on the loop's core) and the socket;
4. ``servo`` - the full real-time servo session: MPC FOH H_t = H_u = 8, the emulator process,
   every topic recorded, as ``hil servo run --realtime`` runs it.

For each: the share of skipped ticks, its excess over the bare loop's in the same repeat, the
lateness p99, and (2-4) the ticks whose feedback was stale and the frames that came late.
Then: where the servo run's skipped ticks fell (a whole second of the loop, where a timing
window closes, or elsewhere), its tick breakdown, what the emulator process was granted,
and the status the run would exit with. Then the same session in lockstep, and a real-time
bench session at 100 Hz over Modbus TCP to its emulator process.

Targets (docs/ARCHITECTURE.md, performance), on the medians of ``--repeat`` repeats: the servo
session skips at most the bare loop's share plus 0.01 points, none of its skips is periodic,
and it completes clean (``completed``: no stale feedback, no late frames: ``hil servo run``
exits 0); the lockstep session >= 10x real time; the bench skips no tick. A shared machine
makes every real-time figure noisy: the load average is printed before and after; quote a
quiet machine's. ``--quick``: runs of 0.1 s and one bench cycle of a 0.5 s machining sequence
(seconds in all; figures not worth quoting), and the hops, observed in the wire run.

``--hops``: one more wire run with a second client on the emulator's bus
(``benchkit/bus_observer.py``), which the emulator forwards every frame stamped when it took
it (the master's SYNC, after its wake-up) or sent it (its TPDOs): each cycle's hops, the SYNC's
way to the emulator, the emulator's answer, and the TPDO's wait for the master's read
(negative: it came after the read began, a stale cycle), over all cycles and the stale ones.
"""

from __future__ import annotations

import argparse
import bisect
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from benchkit import add_quick

from hil.bench.run import BenchRunOptions, run_bench
from hil.core.clock import RealtimeClock
from hil.core.doctor import measure_loop
from hil.core.loop import Task
from hil.core.realtime import Hardening, forget_helper_process, register_helper_process
from hil.core.recording.reader import read_session
from hil.core.session import Session
from hil.drivers.canopen import CanDriveMaster
from hil.emulator_process import start_drive_emulator
from hil.protocols.cia301 import SYNC_COB_ID
from hil.servo.config import load_drive_config
from hil.servo.report import FEEDBACK_TIMING
from hil.servo.rig import open_drive
from hil.servo.run import ServoRunOptions, run_servo
from hil.servo.topics import FEEDBACK_SCHEMA, PREDICTION_SCHEMA, command_schema

RATE_HZ = 2000
OBSERVER = Path(__file__).resolve().parent / "benchkit" / "bus_observer.py"
TPDO1_ID = 0x181            # node 1's TPDO1: the first of its answers to a SYNC
STAMP_RESOLUTION_S = 1e-6   # socketcand's stamps are whole microseconds
SKIPPED_POINTS_MAX = 0.01   # the servo session's skipped share: at most the bare loop's + this
LOCKSTEP_MIN = 10.0
# --quick: a 0.5 s machining sequence instead of bench.toml's 28 s one (M1 and M2 then switch
# faster than their 1 s dwell allows, so it is shortened too)
SHORT_SEQUENCE = """[relays]
M1 = { coil = 0, safe = false, dwell_s = 0.2 }
M2 = { coil = 1, safe = false, dwell_s = 0.2 }

[sequence]
period_s = 0.5
stages = [{ start_s = 0.0, end_s = 0.25, on = ["M1"] },
          { start_s = 0.25, end_s = 0.5, on = ["M1", "M2"] }]
"""
#: a loaded 2-core box: stale feedback is counted, not fatal, here (the watchdog and the
#: safety net's stale share)
TOLERANT = {"master": {"stale_cycles": 100_000}, "safety": {"stale_share_max": 1.0}}
RUNS = ("bare", "recorder", "wire", "servo")
LABELS = {"bare": "bare 2 kHz loop, hardened (hil doctor) [baseline]",
          "recorder": "+ recording a servo tick (writer process)",
          "wire": "+ the drive emulator process over socketcand",
          "servo": "real-time servo session, MPC, recorded"}


def bare_loop(_tmp: Path, seconds: float) -> dict[str, Any]:
    """The bare loop, hardened."""
    hardening = Hardening()
    hardening.apply()
    try:
        loop = measure_loop(RATE_HZ, seconds)
    finally:
        hardening.restore()
    return {"missed_pct": loop["missed_pct"], "p99_us": loop["p99_us"]}


class RecordedTick(Task):
    """Record phase: the three messages a servo tick records (packed rows, MPC's prediction)."""

    def __init__(self, session: Session) -> None:
        super().__init__("tick")
        self.feedback = session.topic("/drive/feedback", FEEDBACK_SCHEMA, high_rate=True)
        self.command = session.topic("/drive/command", command_schema("current"),
                                     high_rate=True)
        self.prediction = session.topic("/mpc/prediction", PREDICTION_SCHEMA, high_rate=True)
        self.k = 0
        self.y_pred = [0.01 * i for i in range(50)]

    def record(self, t_ns: int) -> None:
        k, x = self.k, self.k * 1e-3
        self.feedback.log(t_ns, (x, 2.0 * x, 3.0, 4.0, 0x1637, k, True, 33.0))
        self.command.log(t_ns, (k * 5e-4, x, 0.01 * x, 4.0, None, 20.0, "unconstrained"))
        if k % 10 == 0:
            self.prediction.log(t_ns, (k * 5e-4, self.y_pred[:8], self.y_pred))
        self.k += 1


class WireTick(Task):
    """The servo tick's CAN cycle alone: the TPDOs of the last SYNC, then RPDO (0 mA) + SYNC;
    a first cycle before the clock starts, as a servo run does. ``cycles``: for each SYNC of
    the loop, when it was sent, when its TPDOs were read (wall clock, s) and whether they were
    fresh."""

    def __init__(self, master: CanDriveMaster) -> None:
        super().__init__("tick")
        self.master = master
        self.stale = 0
        self.cycles: list[tuple[float, float, bool]] = []
        self._sent: float | None = None

    def prime(self) -> None:
        self.master.prime()

    def read(self, t_ns: int) -> None:
        began = time.time()
        fresh = self.master.receive_feedback().fresh
        self.stale += not fresh
        if self._sent is not None:
            self.cycles.append((self._sent, began, fresh))

    def write(self, t_ns: int) -> None:
        self._sent = time.time()
        self.master.send_set_point(0.0)


def loop_session(tmp: Path, seconds: float, name: str,
                 tasks: Callable[[Session], list[Task]]) -> tuple[Session, dict[str, Any]]:
    """A hardened real-time session of ``tasks`` (built for it): the session (closed) and
    its loop's figures."""
    session = Session(str(tmp / f"{name}.mcap"), RealtimeClock(), 1.0 / RATE_HZ, kind="bench")
    try:
        for task in tasks(session):
            session.add_task(task)
        session.run(duration_s=seconds)
    finally:
        session.close()
    stats = session.loop.summary()["tick"]
    scheduled = stats["runs"] + stats["missed"]
    return session, {"missed_pct": 100.0 * stats["missed"] / scheduled,
                     "p99_us": stats["lateness_us"]["p99"]}


def recorder_loop(tmp: Path, seconds: float) -> dict[str, Any]:
    _, figures = loop_session(tmp, seconds, "recorder", lambda s: [RecordedTick(s)])
    return figures


def wire_loop(tmp: Path, seconds: float, observe: bool = False) -> dict[str, Any]:
    """The wire run; ``observe``: a second client of the emulator's bus records every frame
    with the emulator's stamp, for the hops of each cycle (``hops``)."""
    with start_drive_emulator(harden=True) as emulator:
        observer = start_observer(emulator.url) if observe else None
        master = open_drive(emulator.url, load_drive_config(overrides=TOLERANT))
        try:
            master.start()
            tick = WireTick(master)

            def tasks(session: Session) -> list[Task]:
                session.add_component(master)
                return [tick]

            _, figures = loop_session(tmp, seconds, "wire", tasks)
        finally:
            master.close()
    figures = {**figures, "stale": tick.stale, "late_frames": master.stats.late_frames}
    if observer is not None:
        figures["hops"] = cycle_hops(tick.cycles, observed_frames(observer))
    return figures


def start_observer(url: str) -> subprocess.Popen[str]:
    """:mod:`benchkit.bus_observer` on the bus at ``url``, in raw mode once this returns, kept
    off the loop's core (an ordinary process, as a helper)."""
    host, _, port = url.removeprefix("socketcand://").rpartition(":")
    observer = subprocess.Popen([sys.executable, str(OBSERVER), host, port], text=True,
                                stdout=subprocess.PIPE)
    assert observer.stdout is not None
    if observer.stdout.readline().strip() != "ready":
        observer.kill()
        raise RuntimeError("the bus observer did not start")
    register_helper_process(observer.pid, "observer")
    return observer


def observed_frames(observer: subprocess.Popen[str]) -> list[tuple[int, float]]:
    """What the observer saw, once the emulator has stopped (which ends its connection)."""
    out, _ = observer.communicate(timeout=60)
    forget_helper_process(observer.pid)
    return [(can_id, stamp) for can_id, stamp in json.loads(out)]


def cycle_hops(cycles: list[tuple[float, float, bool]], frames: list[tuple[int, float]]
               ) -> dict[str, dict[str, list[float]]]:
    """Each cycle's hops [us]: the SYNC from the master's send to the emulator taking it, the
    emulator's answer (its TPDO1 sent), and from there to the master's read of the cycle
    (negative: the TPDO came after the read began, a stale cycle), for all cycles and for the
    stale ones."""
    syncs = [stamp for can_id, stamp in frames if can_id == SYNC_COB_ID]
    tpdos = [stamp for can_id, stamp in frames if can_id == TPDO1_ID]
    hops: dict[str, dict[str, list[float]]] = {"all": {}, "stale": {}}
    for sent, read, fresh in cycles:
        i = bisect.bisect_left(syncs, sent - STAMP_RESOLUTION_S)
        j = bisect.bisect_left(tpdos, syncs[i]) if i < len(syncs) else len(tpdos)
        if j >= len(tpdos):
            continue
        took, answered = syncs[i], tpdos[j]
        for group in ("all",) if fresh else ("all", "stale"):
            for hop, value in (("SYNC sent -> emulator took it", took - sent),
                               ("emulator took it -> TPDO sent", answered - took),
                               ("TPDO sent -> master read the cycle", read - answered)):
                hops[group].setdefault(hop, []).append(value * 1e6)
    return hops


def servo_session(tmp: Path, seconds: float, realtime: bool = True,
                  controller: Any = "mpc") -> dict[str, Any]:
    out = tmp / f"servo-{'rt' if realtime else 'lockstep'}.mcap"
    result = run_servo(ServoRunOptions(
        controller=controller, ert="foh", ht=8, hu=8, duration_s=seconds,
        realtime=realtime, out=str(out), drive_overrides=TOLERANT))
    loop = result.loop["servo"]
    session = read_session(out)
    timing = [m for _, m in session.topic("/loop/servo/timing")]
    feedback = FEEDBACK_TIMING.section(session).get("/drive/feedback", {})
    phases = {phase: [float(np.percentile(v, q)) for q in (50, 90, 99)] if len(v) else []
              for phase in ("read", "compute", "write", "record")
              for v in [np.concatenate([np.asarray(m.get(f"{phase}_us", []), float)
                                        for m in timing] or [np.empty(0)])]}
    skips = [m["data"] for _, m in session.topic("/events") if m["kind"] == "loop.overrun"]
    window = round(RATE_HZ * 1.0)  # the loop's timing window: 1 s
    scheduled = loop["runs"] + loop["missed"]
    return {"missed_pct": 100.0 * loop["missed"] / scheduled, "p99_us":
            loop["lateness_us"]["p99"], "p50_us": loop["lateness_us"]["p50"],
            "factor": result.kpis["realtime_factor"] or 0.0,
            "stale": result.kpis["stale_feedback"],
            "late_frames": result.kpis["faults"]["late_frames"],
            "status": result.kpis["status"], "ticks": result.kpis["ticks"],
            "step_us": result.kpis["step_us"]["median"], "phases": phases,
            "late_side": feedback.get("late_side", "-"),
            "skips": len(skips),
            # a window closes at each whole second after the first: the start's first ticks
            # (caches and the interpreter's specialised code still cold) are not one
            "periodic_skips": sum(1 for s in skips if s["tick"] >= window
                                  and s["tick"] % window <= 2),
            "start_skips": sum(1 for s in skips if s["tick"] <= 2),
            "emulator": session.metadata.get("realtime.emulator", {})}


def bench_session(tmp: Path, cycles: int, config_path: str | None = None) -> dict[str, float]:
    out = tmp / "bench-rt.mcap"
    run_bench(BenchRunOptions(controller="bc", cycles=cycles, realtime=True, out=str(out),
                              config_path=config_path))
    sampler = json.loads(read_session(out).metadata["loop"]["bench_io"])
    return {"missed": sampler["missed"], "runs": sampler["runs"],
            "p99_us": sampler["lateness_us"]["p99"]}


RUNNERS: dict[str, Callable[[Path, float], dict[str, Any]]] = {
    "bare": bare_loop, "recorder": recorder_loop, "wire": wire_loop, "servo": servo_session}


def median_run(runs: list[dict[str, Any]], key: str) -> dict[str, Any]:
    """The run whose ``key`` is the median of ``runs`` (the lower middle one if even)."""
    return sorted(runs, key=lambda run: run[key])[(len(runs) - 1) // 2]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float,
                        help="each real-time run [s] (default 10; 0.1 with --quick)")
    parser.add_argument("--bench-cycles", type=int, help="bench run, 28 s each (default 2; "
                        "one 0.5 s cycle with --quick)")
    parser.add_argument("--repeat", type=int, default=1,
                        help="repeats of the four real-time runs, one after the other (the "
                             "machine's speed drifts: the targets are checked on the medians)")
    parser.add_argument("--hops", action="store_true",
                        help="one more wire run, a second client of the emulator's bus "
                             "recording each frame with the emulator's stamp: each cycle's "
                             "hops (SYNC to the emulator, its answer, back to the master), "
                             "over all cycles and the stale ones")
    add_quick(parser)
    args = parser.parse_args()
    if args.repeat < 1:
        parser.error("--repeat must be >= 1")
    args.seconds = args.seconds or (0.1 if args.quick else 10.0)
    args.bench_cycles = args.bench_cycles or (1 if args.quick else 2)
    cycle_s = 0.5 if args.quick else 28.0
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name in RUNS}
    load = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        hops = None
        for i in range(args.repeat):
            print(f"repeat {i + 1} of {args.repeat}...", file=sys.stderr)
            for name in RUNS:
                if name == "wire" and args.quick and hops is None:
                    # --quick: the observer's path runs too, in the first wire run (figures
                    # not worth quoting: no wire run of its own for it)
                    runs[name].append(wire_loop(tmp, args.seconds, observe=True))
                    hops = runs[name][-1].pop("hops")
                else:
                    runs[name].append(RUNNERS[name](tmp, args.seconds))
        if args.hops and hops is None:  # a run of its own: the observer weighs on the bus
            hops = wire_loop(tmp, args.seconds, observe=True)["hops"]
        lockstep = servo_session(tmp, args.seconds, realtime=False)
        bench_config = None
        if args.quick:
            bench_config = str(tmp / "short-sequence.toml")
            Path(bench_config).write_text(SHORT_SEQUENCE)
        bench = bench_session(tmp, args.bench_cycles, bench_config)
    load.append(os.getloadavg()[0])
    report(args, runs, lockstep, bench, cycle_s, load)
    if hops is not None:
        report_hops(hops)
    return 0


def report_hops(hops: dict[str, dict[str, list[float]]]) -> None:
    """Each hop's quantiles over all cycles, then over the stale ones."""
    print("hops of a wire run's cycles, observed on the bus (a second client: the emulator "
          "forwards it every frame) [us]")
    for group, rows in hops.items():
        if not rows:
            print(f"   {group} cycles: none")
            continue
        count = len(next(iter(rows.values())))
        print(f"   {group} cycles ({count}){'':<19}p50      p99      max")
        for hop, values in rows.items():
            p50, p99 = np.percentile(values, [50, 99])
            print(f"   {hop:<36}{p50:>8.1f} {p99:>8.1f} {max(values):>8.1f}")


def report(args: argparse.Namespace, runs: dict[str, list[dict[str, Any]]],
           lockstep: dict[str, Any], bench: dict[str, float], cycle_s: float,
           load: list[float]) -> None:
    print(f"machine load average (1 min): {load[0]:.2f} before, {load[1]:.2f} after, on "
          f"{os.cpu_count()} CPUs (real-time figures are worth quoting near 0)")
    print(f"real time at {RATE_HZ} Hz, {args.seconds:g} s a run, {args.repeat} repeat(s): "
          "each suspect against the bare loop of the same repeat")
    print(f"{'run':<52}{'skipped %':>10}{'vs bare':>9}{'p99 us':>8}{'stale':>7}"
          f"{'late frames':>12}")
    for i in range(args.repeat):
        bare = runs["bare"][i]["missed_pct"]
        for name in RUNS:
            run = runs[name][i]
            excess = "" if name == "bare" else f"{run['missed_pct'] - bare:+.3f}"
            print(f"{LABELS[name]:<52}{run['missed_pct']:>10.3f}{excess:>9}"
                  f"{run['p99_us']:>8.1f}{run.get('stale', ''):>7}"
                  f"{run.get('late_frames', ''):>12}")
    excess = [servo["missed_pct"] - bare["missed_pct"]
              for servo, bare in zip(runs["servo"], runs["bare"], strict=True)]
    servo = median_run(runs["servo"], "missed_pct")
    median_excess = statistics.median(excess)
    print(f"median of {args.repeat}: the servo session skipped {median_excess:+.3f} points "
          "against the bare loop; its lateness p99 "
          f"{median_run(runs['servo'], 'p99_us')['p99_us']:.1f} us, p50 {servo['p50_us']:.1f} us")
    print(f"   its skips: {servo['skips']} overrun(s), {servo['periodic_skips']} of them at a "
          "whole second of the loop (where its timing window closes), "
          f"{servo['start_skips']} in its first three ticks")
    print(f"   stale feedback {servo['stale']} of {servo['ticks']} ticks (late side "
          f"{servo['late_side']}), late frames {servo['late_frames']}: it would exit as "
          f"'{servo['status']}'")
    print("   the drive emulator's process: " + ("; ".join(
        f"{step} {outcome}" for step, outcome in servo["emulator"].items()) or "-"))
    print("   tick breakdown of that run [us] p50      p90      p99   (write: send, then record)")
    for name, values in servo["phases"].items():
        if values:
            print(f"   {name:<24}" + "".join(f"{v:>9.1f}" for v in values))
    print(f"lockstep servo through the CAN link, MPC, recorded: {lockstep['factor']:.1f}x real "
          f"time (MPC step median {lockstep['step_us']:.0f} us)")
    print(f"real-time bench, 100 Hz over Modbus TCP to the emulator process, "
          f"{args.bench_cycles * cycle_s:g} s: {bench['missed']:.0f} of "
          f"{bench['runs'] + bench['missed']:.0f} ticks skipped, sampler p99 "
          f"{bench['p99_us']:.0f} us")
    clean = all(run["status"] == "completed" for run in runs["servo"])
    print("targets")
    print(f"   servo skipped <= bare + {SKIPPED_POINTS_MAX:g} points (median "
          f"{median_excess:+.3f}): {'met' if median_excess <= SKIPPED_POINTS_MAX else 'MISSED'}")
    print(f"   no periodic overrun ({sum(r['periodic_skips'] for r in runs['servo'])} skip(s) "
          "at a whole second, all runs): "
          f"{'met' if not any(r['periodic_skips'] for r in runs['servo']) else 'MISSED'}")
    print("   every servo session completes clean (stale, late frames: " + ", ".join(
        f"{r['stale']}/{r['late_frames']}" for r in runs["servo"]) +
          f"): {'met' if clean else 'MISSED'}")
    print(f"   lockstep >= {LOCKSTEP_MIN:g}x ({lockstep['factor']:.1f}x): "
          f"{'met' if lockstep['factor'] >= LOCKSTEP_MIN else 'MISSED'}")
    print(f"   bench skips no tick ({bench['missed']:.0f}): "
          f"{'met' if bench['missed'] == 0 else 'MISSED'}")


if __name__ == "__main__":
    sys.exit(main())
