"""Fault soak: seeded random faults from docs/FAULTS.md against both emulators, over the wire.

1. Bench: one lockstep ``hil bench run`` (BC controller) against the in-process emulator over
   Modbus TCP, ``--bench-minutes`` of session time (default 2; the issue's soak is 10), with
   one random bench fault at a time in its config's ``[faults]`` table.
2. Servo: one real-time ``hil servo run`` (PID, hold position) over socketcand against a drive
   emulator process, ``--servo-s`` seconds (default 10; the issue's soak is 60), with random
   non-fatal drive faults (dropped and late TPDOs), then ``silent`` in its last second.

For each fault: injected (the emulator's record), detected (the bridge's events or counters in
its window), and the reaction. Messages lost: samples missing from the session, split into
those inside a fault's window (what the fault destroyed, reported) and outside every window
(silent losses). Target: every fault detected, zero silent losses. Baselines from the same
run: the bench session again without faults (its losses are the machine's, not the faults');
for the servo, the stale cycles outside every fault window (a loaded machine's, each one
counted in ``stale_feedback``). A welded relay nothing asks to switch is "not exercised":
no read-back can tell it from a healthy one.

3. Bench over a noisy RTU line: lockstep bench sessions (``--noisy-s`` seconds of session time
   each) against ``hil emulate bench --serial`` through a null-modem cable that flips a share
   of the bytes both ways (the ``noise`` fault: clean, 1 in 5000, 1 in 500, 2 %): bytes flipped,
   requests, retries per thousand requests, how the session ended and its realtime factor.
   The target: a flipped byte costs a retry, never the session.

``--quick``: one bench machine cycle (28 s of session time) without the no-fault baseline, a 1 s
servo run after a 1 s lead (the final ``silent`` alone), and one 0.1 s noisy-line session,
2 % (a few dozen requests: it still costs retries; the clean line is the full run's baseline;
seconds; figures not worth quoting, and the verdict does not set the exit status: a fault
missed on a loaded machine is a figure there).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchkit import add_quick  # noqa: E402

from hil import api  # noqa: E402
from hil.bench.config import load_bench_config, parse_bench_config  # noqa: E402
from hil.bench.rig import attach_bench  # noqa: E402
from hil.core.clock import SimClock  # noqa: E402
from hil.core.config import deep_merge  # noqa: E402
from hil.core.recording.reader import read_session  # noqa: E402
from hil.core.session import Session  # noqa: E402
from hil.emulators.faults import parse_fault  # noqa: E402
from hil.emulators.null_modem import NullModem  # noqa: E402
from hil.errors import HilError  # noqa: E402

CYCLE_S = 28.0  # the machining sequence's period
MARGIN_S = 1.5  # a reaction counts for a fault if it comes within this after its window
BENCH_DETECTIONS = {  # kind -> events that show the bridge noticed
    "drop": ("link.retried", "link.lost", "relay.write_failed"),
    "close": ("link.retried", "link.lost", "relay.write_failed"),
    "delay": ("link.retried", "link.lost", "relay.write_failed"),
    "exception": ("link.retried", "link.lost", "relay.write_failed"),
    "freeze": ("meter.stale",),
    "weld": ("relay.stuck", "relay.mismatch"),
}


def bench_schedule(rng: random.Random, session_s: float) -> list[str]:
    """One fault at a time, every 6-10 s after the last one ended, windows 0.3-3 s; the kinds
    in a shuffled order, each once before any twice."""
    faults, t = [], 5.0
    kinds: list[str] = []
    while t < session_s - 8.0:
        if not kinds:
            kinds = list(BENCH_DETECTIONS)
            rng.shuffle(kinds)
        kind = kinds.pop()
        t = round(t, 2)
        length = round(rng.uniform(0.3, 3.0), 2)
        end = round(t + length, 2)
        params = {  # sparse drops: every lost answer costs a time-out of wall time
            "drop": lambda: f":every={rng.choice([1, 10, 20])}",
            "close": lambda: "",
            "delay": lambda: f":ms={rng.choice([150, 300])}",
            "exception": lambda: f":code={rng.choice([4, 6])}",
            "freeze": lambda: ":device=meter",
            "weld": lambda: f":relay={rng.choice(['P1', 'P2'])}",
        }[kind]()
        if kind == "weld":  # long enough for the controller to switch it
            end = round(t + 10.0, 2)
        faults.append(f"{kind}@{t:g}-{end:g}{params}")
        t = end + rng.uniform(6.0, 10.0)
    return faults


def windows_of(events: list[dict[str, Any]]) -> list[tuple[str, float, float]]:
    """(spec, start, end) of every fault the emulator injected; in lockstep the plant's time
    is the session's."""
    out = []
    for event in events:
        if event["kind"] != "fault.injected":
            continue
        spec = event["data"]["fault"]
        end = spec.split("@")[1].split(":")[0].partition("-")[2]
        out.append((spec, event["data"]["plant_t_s"], float(end or "inf")))
    return out


def soak_bench(minutes: float, seed: int, faults: bool, tmp: Path) -> dict[str, Any]:
    cycles = max(1, round(minutes * 60 / CYCLE_S))
    schedule = bench_schedule(random.Random(seed), cycles * CYCLE_S) if faults else []
    config = tmp / f"bench-{faults}.toml"
    config.write_text("[faults]\nschedule = " + json.dumps(schedule) + "\n")
    out = tmp / f"bench-{faults}.mcap"
    wall = time.perf_counter()
    stopped = None
    try:
        kpis = api.run_bench("bc", cycles=cycles, config_path=str(config), out=str(out))
    except HilError as exc:  # the bridge stopped the run: its reaction, the session is there
        if not out.exists():
            raise
        kpis, stopped = {}, str(exc).split(" (session")[0]
    wall = time.perf_counter() - wall
    data = read_session(out)
    span = data.time_range_ns()
    t_start = span[0] if span else 0
    events = [m | {"t_s": (t - t_start) / 1e9} for t, m in data.topic("/events")]
    if stopped is not None:
        at = next((e["t_s"] for e in events if e["kind"] == "session.stop"), math.nan)
        kpis["stop_reason"] = f"stopped by the bridge at {at:.1f} s: {stopped}"
    windows = windows_of(events)
    relays = [((t - t_start) / 1e9, m) for t, m in data.topic("/bench/relays")]
    rows = []
    for spec, start, end in windows:
        kind = spec.split("@")[0]
        seen = sorted({e["kind"] for e in events if e["kind"] in BENCH_DETECTIONS[kind]
                       and start <= e["t_s"] <= end + MARGIN_S})
        if kind == "weld" and not seen and not switched(relays, spec, start, end):
            seen = ["(not exercised: nothing asked the relay to switch in its window)"]
        rows.append((spec, seen))
    power_t = np.array([t for t, _ in data.topic("/bench/power")], dtype=np.int64)
    # the grid's sample at a window's start may sit a rounding error before it
    caused = [(s - 0.011, e + MARGIN_S) for _, s, e in windows]
    lost_at = [e["t_s"] for e in events if e["kind"] == "link.lost"]
    back_at = [e["t_s"] for e in events if e["kind"] in ("link.restored", "session.stop")]
    for lost in lost_at:  # a loss a fault caused lasts until the link is back
        if any(s <= lost <= e for s, e in caused):
            caused.append((lost, min((b for b in back_at if b >= lost), default=math.inf)))
    lost_in, silent = missing_samples(power_t, t_start, 10_000_000, caused)
    return {"cycles": cycles, "session_s": cycles * CYCLE_S, "wall_s": wall, "rows": rows,
            "scheduled": len(schedule), "lost_in": lost_in, "silent": silent,
            "faults": kpis.get("faults"), "stop": kpis.get("stop_reason"),
            "samples": int(power_t.size)}


def switched(relays: list[tuple[float, dict[str, int]]], spec: str, start: float,
             end: float) -> bool:
    """Whether anything asked the welded relay of ``spec`` to change during its window."""
    name = spec.split("relay=")[1].split(",")[0]
    return any(m[f"{name}_commanded"] != m[name] for t, m in relays if start <= t <= end)


def missing_samples(t_ns: np.ndarray, t0_ns: int, period_ns: int,
                    windows: list[tuple[float, float]]) -> tuple[int, list[float]]:
    """Samples of a ``period_ns`` grid with no message: how many inside a window, and the
    times (s) of those outside all of them."""
    if t_ns.size == 0:
        return 0, []
    grid = np.arange(int(t_ns[0]), int(t_ns[-1]) + 1, period_ns)
    have = np.isin(grid, t_ns)
    t_s = (grid[~have] - t0_ns) / 1e9
    inside = np.zeros(t_s.shape, dtype=bool)
    for start, end in windows:
        inside |= (t_s >= start) & (t_s <= end)
    return int(inside.sum()), [round(float(t), 2) for t in t_s[~inside]]


def soak_servo(seconds: float, seed: int, tmp: Path, lead: float = 8.0) -> dict[str, Any]:
    """Random dropped and late TPDOs for ``seconds``, then ``silent``: the run must end on it.
    Fault times are the emulator's (seconds since it started), so the schedule starts after a
    lead that covers the run's start-up on a loaded machine."""
    rng = random.Random(seed)
    schedule: list[str] = []
    t = lead + 1.0
    while t < lead + seconds - 2.0:
        length = round(rng.uniform(0.1, 0.5), 2)
        every = rng.choice([2, 3, 5])
        schedule.append(rng.choice([f"drop_tpdo@{t:.2f}-{t + length:.2f}:every={every}",
                                    f"delay_tpdo@{t:.2f}-{t + length:.2f}:ms=2"]))
        t += length + rng.uniform(1.0, 2.0)
    schedule.append(f"silent@{lead + seconds - 1.0:.2f}")
    config = tmp / "drive.toml"
    # watchdogs relaxed for a loaded machine: a drive heartbeat missed for 3 s, 400 stale
    # cycles; the drive's own for the master's heartbeat and SYNC 5 s
    config.write_text("[master]\nstale_cycles = 400\nheartbeat_timeout_ms = 5000\n"
                      "drive_heartbeat_ms = 1000\nrx_timeout_us = 2000\n"
                      "[emulator]\nsync_loss_timeout_ms = 5000\n")
    out = tmp / "servo.mcap"
    error = ""
    with api.start_drive_emulator(config, faults=schedule) as emulator:
        try:
            api.run_servo("pid", drive=emulator.url, realtime=True, duration_s=seconds + lead,
                          reference="hold:position=0", drive_config=str(config),
                          out=str(out))
        except Exception as exc:  # the final silent fault ends the run: the reaction
            error = str(exc).split(" (session")[0]
        injected = emulator.fault_events()
    if not out.exists():  # the run ended before its session began (on a loaded machine its
        # start can outlast the lead, into the final silent fault): its error is the reaction
        return {"scheduled": len(schedule), "injected": len(injected), "detected": [],
                "error": f"{error} (before the session began)", "ticks": 0, "stale_in": 0,
                "stale_out": 0, "events": []}
    data = read_session(out)
    feedback = data.topic("/drive/feedback")
    stale_t = np.array([t for t, m in feedback if not m["fresh"]], dtype=np.int64) / 1e9
    windows = []  # in the session's time (unix ns), from the emulator's unix time stamps
    for line in injected:
        spec, at = line.split(" injected at t=")
        t_s, unix_s = float(at.split(" ")[0]), float(at.split("unix time ")[1].rstrip(")"))
        end_text = spec.split("@")[1].split(":")[0].partition("-")[2]
        windows.append((spec, unix_s, unix_s + (float(end_text) - t_s if end_text else 1.0)))
    inside = np.zeros(stale_t.shape, dtype=bool)
    for _, start, end in windows:
        inside |= (stale_t >= start) & (stale_t <= end + 0.05)
    detected = [spec for spec, start, end in windows
                if np.any((stale_t >= start) & (stale_t <= end + 0.05))]
    return {"scheduled": len(schedule), "injected": len(injected), "error": error,
            "detected": detected, "ticks": len(feedback), "stale_in": int(inside.sum()),
            "stale_out": int((~inside).sum()),
            "events": sorted({m["kind"] for _, m in data.topic("/events")})}


#: the noisy line's cases: the share of the bytes flipped each way (0: a clean line)
NOISE_RATES = (0.0, 1 / 5000, 1 / 500, 0.02)
#: over RTU poll what the bench needs (as the bench guide advises): the apparent powers, levels at
#: 10 Hz
RTU_POLLS = {"meter": {"poll": ["va_l1", "va_l2", "va_l3", "total_va"]},
             "sampling": {"levels_every": 10}}


def noisy_line(rate: float, seconds: float, seed: int, tmp: Path) -> dict[str, Any]:
    """A lockstep bench session of ``seconds`` (sequence playing, no controller) over Modbus
    RTU against ``hil emulate bench --serial`` through a null-modem cable flipping ``rate`` of
    the bytes both ways: what the cable carried and flipped, the requests, retries and frames
    passed over, how it ended, its realtime factor."""
    config = parse_bench_config(deep_merge(load_bench_config().data, RTU_POLLS))
    faults = [parse_fault(f"noise@0:rate={rate!r},seed={seed}")] if rate else []
    with NullModem(faults=faults) as modem:
        emulator = subprocess.Popen(
            [sys.executable, "-m", "hil", "emulate", "bench", "--serial", modem.ports[1]],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL,
            text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
        try:
            assert emulator.stdout is not None
            emulator.stdout.readline()  # listening
            session = Session(str(tmp / f"noisy-{rate}.mcap"), SimClock(), 0.01, kind="bench",
                              config=config.data, handle_signals=False)
            rig = attach_bench(session, config, f"modbus-rtu://{modem.ports[0]}")
            wall = time.perf_counter()
            try:
                session.run(duration_s=seconds)
            finally:
                wall = time.perf_counter() - wall
                rig.close()
                session.close()
        finally:
            emulator.terminate()
            emulator.wait(10)
    bench = rig.bench
    return {"carried": sum(modem.carried), "flipped": sum(modem.flipped),
            "requests": bench.requests, "retries": bench.retries,
            "passed_over": bench._driver.link.discarded,
            "ended": session.loop.stop_reason or "completed",
            "factor": seconds / wall if wall > 0 else math.nan}


def noisy_line_report(seconds: float, seed: int, rates: tuple[float, ...], tmp: Path) -> None:
    print(f"== bench over a noisy RTU line: lockstep, {seconds:g} s of session time each, "
          f"seed {seed}")
    print(f"  {'bytes flipped':<14} {'flipped/carried':>18} {'requests':>9} {'retries':>8} "
          f"{'per 1000 req':>12} {'passed over':>11} {'realtime':>9}  ended")
    for rate in rates:
        case = noisy_line(rate, seconds, seed, tmp)
        share = "clean" if not rate else (f"1 in {1 / rate:.0f}" if rate < 0.01
                                          else f"{rate:.0%}")
        per_1000 = 1000 * case["retries"] / max(1, case["requests"])
        print(f"  {share:<14} {case['flipped']:>8}/{case['carried']:<9} {case['requests']:>9} "
              f"{case['retries']:>8} {per_1000:>12.1f} {case['passed_over']:>11} "
              f"{case['factor']:>8.2f}x  {case['ended']}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bench-minutes", type=float,
                        help="bench session time, minutes (default 2, the issue's soak: 10; "
                             "one 28 s cycle with --quick)")
    parser.add_argument("--servo-s", type=float,
                        help="servo run, seconds of faults (default 10, the issue's soak: 60; "
                             "1 with --quick)")
    parser.add_argument("--noisy-s", type=float,
                        help="session time of each noisy-line case, seconds (default 5; 0.1 "
                             "with --quick)")
    parser.add_argument("--seed", type=int, default=1)
    add_quick(parser)
    args = parser.parse_args()
    args.bench_minutes = args.bench_minutes or (CYCLE_S / 60 if args.quick else 2.0)
    args.servo_s = args.servo_s or (1.0 if args.quick else 10.0)
    args.noisy_s = args.noisy_s or (0.1 if args.quick else 5.0)
    with tempfile.TemporaryDirectory() as directory:
        tmp = Path(directory)
        print(f"== bench: lockstep, {args.bench_minutes:.3g} min of session time, seed "
              f"{args.seed}")
        base = None if args.quick else soak_bench(args.bench_minutes, args.seed, False, tmp)
        soak = soak_bench(args.bench_minutes, args.seed, True, tmp)
        exercised = [(spec, seen) for spec, seen in soak["rows"]
                     if not (seen and seen[0].startswith("(not exercised"))]
        detected = sum(1 for _, seen in exercised if seen)
        for spec, seen in soak["rows"]:
            verdict = ("" if seen[:1] and seen[0].startswith("(") else "detected: ") + \
                ", ".join(seen) if seen else "NOT DETECTED"
            print(f"  {spec:<36} {verdict}")
        print(f"  faults scheduled {soak['scheduled']}, injected {len(soak['rows'])}, "
              f"exercised {len(exercised)}, detected {detected}")
        print(f"  reactions (KPIs): {soak['faults']}; stop: {soak['stop']}")
        baseline = ("baseline without faults: skipped (--quick)" if base is None else
                     f"baseline without faults: {base['lost_in'] + len(base['silent'])} lost of "
                     f"{base['samples']}")
        print(f"  power samples lost: {soak['lost_in']} inside fault windows and the link "
              f"losses they caused (reported), {len(soak['silent'])} outside (silent"
              f"{': at ' + str(soak['silent'][:5]) + ' s' if soak['silent'] else ''}); "
              f"{baseline}")
        print(f"  wall time {soak['wall_s']:.1f} s with faults" + (
            "" if base is None else f", {base['wall_s']:.1f} s without") +
            f" ({soak['session_s']:g} s of session time)")
        print(f"== servo: real time over socketcand, {args.servo_s:g} s with faults")
        servo = soak_servo(args.servo_s, args.seed, tmp, lead=1.0 if args.quick else 8.0)
        print(f"  faults scheduled {servo['scheduled']}, injected {servo['injected']}, "
              f"detected (stale cycles in their window) {len(servo['detected'])}")
        print(f"  stale cycles: {servo['stale_in']} inside fault windows, {servo['stale_out']} "
              f"outside (the machine's, each counted in stale_feedback) of {servo['ticks']}")
        print(f"  the final 'silent' fault: {servo['error'] or 'NOT DETECTED'}")
        print(f"  events: {servo['events']}")
        noisy_line_report(args.noisy_s, args.seed,
                          (0.02,) if args.quick else NOISE_RATES, tmp)
    if args.quick:
        return 0
    return 0 if detected == len(exercised) and not soak["silent"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
