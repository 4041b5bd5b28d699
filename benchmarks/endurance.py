"""Endurance (memory): does a long session keep its memory constant?

Two lockstep sessions, each in a child process of its own:

* servo: ``hil servo run --controller mpc`` (sine 2 deg / 10 Hz, emulated drive over CAN,
  /mpc/prediction every 10th tick as in real time), default 3 simulated minutes;
* bench: ``hil bench run --controller eec`` (emulated Modbus bench), default 64 machine
  cycles (about 30 simulated minutes).

The child reads its resident set size (/proc/self/statm) at every whole simulated minute,
when the loop publishes its timing window. Printed per session: RSS after the first
simulated minute and its growth after it (target: <= 5 MB over the whole soak), bytes of the
session file per simulated hour, the messages waiting in the recorder's queue at each minute
(in lockstep it holds up to 100,000 before the loop waits for the writer), and the loop's
lateness and compute p99 per simulated minute from the session's /loop/*/timing topics
(lockstep: lateness is 0 by construction; compute shows whether a step slows down as the run
ages). ``--baseline-code DIR`` runs the same children on another checkout (e.g. ``git
archive`` of main) in the same run, for the before figures. ``--hours H`` sets both sessions
to H simulated hours; ``--full`` is the issue's soak: 1 h servo, 24 h bench (hours of wall
time). ``--quick``: 2 s of each session (the bench's: not a whole 28 s machine cycle), sampled
every simulated second instead of every minute (seconds; figures not worth quoting).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from benchkit import add_quick

from hil.core.recording.cdr import CdrDecoder, parse_ros2msg

ROOT = Path(__file__).resolve().parents[1]
CODE_ENV = "HIL_ENDURANCE_CODE"  # the checkout a child imports hil from
sys.path.insert(0, os.environ.get(CODE_ENV, str(ROOT)))

GROWTH_TARGET_MB = 5.0
MACHINE_CYCLE_S = 28.0  # the bench's default sequence period (hil/configs/bench.toml)
PAGE = os.sysconf("SC_PAGE_SIZE")

def rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE


# ------------------------------------------------------------------------------- the child
def child(kind: str, seconds: float, out: str, sample_s: float = 60.0) -> None:
    """Run one session, printing one JSON line: RSS at each whole ``sample_s`` of simulated
    time (a minute but with ``--quick``)."""
    from hil.core.loop import FixedRateLoop

    assert Path(sys.modules["hil"].__file__ or "").resolve().is_relative_to(
        Path(os.environ.get(CODE_ENV, ROOT)).resolve()), "hil imported from the wrong checkout"
    samples: list[tuple[int, int]] = []  # (RSS bytes, messages waiting in the recorder)
    publish = FixedRateLoop._publish_windows

    # instrumentation of this benchmark only: the loop publishes its timing window once per
    # simulated second, which is where a whole simulated minute is noticed
    def publish_and_sample(loop: FixedRateLoop, final: bool) -> None:
        publish(loop, final)
        minute = loop.ticks * loop.base_period_ns // round(sample_s * 1e9)
        queue = getattr(getattr(loop, "_recorder", None), "_queue", ())
        while len(samples) < minute:
            samples.append((rss_bytes(), len(queue)))

    FixedRateLoop._publish_windows = publish_and_sample  # type: ignore[method-assign]
    start = time.perf_counter()
    if kind == "servo":
        from hil.servo.run import ServoRunOptions, run_servo
        run_servo(ServoRunOptions("mpc", duration_s=seconds, out=out, prediction_every=10))
    else:
        from hil.bench.run import BenchRunOptions, run_bench
        cycles = round(seconds / MACHINE_CYCLE_S)  # whole machine cycles, or less than one
        run_bench(BenchRunOptions(controller="eec", cycles=max(1, cycles),
                                  duration_s=None if cycles else seconds, out=out))
    print(json.dumps({"rss": samples, "wall_s": time.perf_counter() - start,
                      "final_rss": rss_bytes()}))


# ------------------------------------------------------------------------------ the parent
def run_child(kind: str, seconds: float, code: Path, out: str, sample_s: float) -> dict:
    env = {**os.environ, CODE_ENV: str(code)}
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", kind,
                           "--seconds", str(seconds), "--out", out,
                           *(["--sample-s", str(sample_s)] if sample_s != 60.0 else [])],
                          env=env, cwd=code, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{kind} child failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def timing_per_minute(path: str, sample_s: float = 60.0) -> tuple[list[float], list[float]]:
    """Lateness and compute p99 [us] per simulated minute (``sample_s``), over every task of
    the loop."""
    from mcap.reader import make_reader  # indexed read of the timing topics only

    lateness: dict[int, list[np.ndarray]] = {}
    compute: dict[int, list[np.ndarray]] = {}
    start = None  # the first window ends one window (1 s) after the loop started
    with open(path, "rb") as f:
        reader = make_reader(f)
        topics = [c.topic for c in reader.get_summary().channels.values()
                  if c.topic.startswith("/loop/") and c.topic.endswith("/timing")]
        decoders: dict[int, Any] = {}
        for schema, channel, message in reader.iter_messages(topics=topics,
                                                              log_time_order=True):
            start = message.log_time - 1_000_000_000 if start is None else start
            minute = max(0, message.log_time - start - 1) // round(sample_s * 1e9)
            if channel.id not in decoders:  # JSON, or CDR with a ros2msg schema (the default)
                decoders[channel.id] = (
                    CdrDecoder(parse_ros2msg(schema.data.decode())).decode
                    if channel.message_encoding == "cdr" and schema is not None else json.loads)
            window = decoders[channel.id](message.data)
            lateness.setdefault(minute, []).append(np.asarray(window["lateness_us"], float))
            # a run's whole step: the sum of its phases (sessions before phases: compute_us)
            phases = [np.asarray(window.get(f"{p}_us", []), float)
                      for p in ("read", "compute", "write", "record")]
            phases = [a for a in phases if a.size] or [np.empty(0)]
            compute.setdefault(minute, []).append(np.sum(phases, axis=0))

    def p99(per: dict[int, list[np.ndarray]]) -> list[float]:
        return [float(np.percentile(np.concatenate(per[m]), 99)) for m in sorted(per)
                if sum(a.size for a in per[m])]
    return p99(lateness), p99(compute)


def soak(kind: str, seconds: float, code: Path, label: str, sample_s: float = 60.0) -> float:
    period = "minute" if sample_s == 60.0 else f"{sample_s:g} s"
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, f"{kind}.mcap")
        result = run_child(kind, seconds, code, out, sample_s)
        size = os.path.getsize(out)
        lateness, compute = timing_per_minute(out, sample_s)
    rss = np.asarray([r for r, _ in result["rss"]], float) / 1e6
    queued = [q for _, q in result["rss"]]
    growth = float(rss[1:].max() - rss[0]) if rss.size > 1 else 0.0
    length = f"{seconds / 60:.0f} simulated min" if seconds >= 60 else f"{seconds:g} simulated s"
    print(f"  {label:<6} {kind}: {length} in {result['wall_s']:.0f} s; "
          f"RSS after the first {period} {rss[0]:.1f} MB, growth after it {growth:+.2f} MB "
          f"(target <= {GROWTH_TARGET_MB:g} MB: {'ok' if growth <= GROWTH_TARGET_MB else 'MISSED'})"
          f"; session file {size / 1e6:.1f} MB = {size / (seconds / 3600) / 1e9:.2f} GB/h")
    step = max(1, rss.size // 12)
    print(f"         RSS per {period} [MB]: "
          + " ".join(f"{m + 1}:{v:.1f}" for m, v in list(enumerate(rss))[::step]))
    print("         messages queued in the recorder: "
          + " ".join(f"{q}" for q in queued[::step]))
    print(f"         lateness p99 per {period} [us]: "
          + " ".join(f"{v:.0f}" for v in lateness[::step]))
    print(f"         compute p99 per {period} [us]: "
          + " ".join(f"{v:.0f}" for v in compute[::step]))
    return growth


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hours", type=float, help="simulated hours of both sessions")
    parser.add_argument("--full", action="store_true", help="1 h servo and 24 h bench")
    add_quick(parser)
    parser.add_argument("--baseline-code", type=Path,
                        help="another checkout to run the same sessions on, for comparison")
    parser.add_argument("--child", choices=("servo", "bench"), help=argparse.SUPPRESS)
    parser.add_argument("--seconds", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    parser.add_argument("--sample-s", type=float, default=60.0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child(args.child, args.seconds, args.out, args.sample_s)
        return 0
    if args.quick and (args.full or args.hours):
        parser.error("--quick goes with neither --full nor --hours")
    lengths = {"servo": 3 * 60.0, "bench": 64 * MACHINE_CYCLE_S}
    sample_s = 1.0 if args.quick else 60.0
    if args.quick:
        lengths = {"servo": 2.0, "bench": 2.0}
    if args.full:
        lengths = {"servo": 3600.0, "bench": 24 * 3600.0}
    if args.hours:
        lengths = dict.fromkeys(lengths, args.hours * 3600.0)
    period = "minute" if sample_s == 60.0 else f"{sample_s:g} s"
    print(f"Endurance: RSS sampled every simulated {period} (lockstep sessions)")
    growths = []
    for kind, seconds in lengths.items():
        if args.baseline_code is not None:
            soak(kind, seconds, args.baseline_code.resolve(), "before", sample_s)
        growths.append(soak(kind, seconds, ROOT, "now", sample_s))
    worst = max(growths)
    print(f"  worst RSS growth after the first {period}: {worst:.2f} MB "
          f"(target <= {GROWTH_TARGET_MB:g} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
