"""Recorder cost in the loop process (Topic.log + the per-tick hand-over to the writer
process) and sustained throughput, vs writing directly.

Baseline: what a loop would pay writing each message itself (json.dumps + mcap add_message on
the calling thread). Targets (the project's): <= 5 us per message on the loop thread, >= 50k msg/s.
The hand-over runs every 4 messages here, as a 2 kHz servo tick logs about that many, and the
messages are stamped as such a tick stamps them (a lockstep run, 200,000 messages = 25 s of
session time written in seconds). The writer closes a chunk at each second of session time
(``chunk_span_s``): the same streams without that bound (chunks by size and wall time only,
as before it), alternated with it, are the baseline of its cost: the writer process's CPU
time, chunks and file size, for that servo stream and a bench one (100 Hz, 28 s).
``--quick``: 10,000 messages instead of 200,000 (a second or two; figures not worth quoting).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import tempfile
import time
from dataclasses import dataclass

from benchkit import add_quick
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from hil.core.recording.recorder import Recorder

N = 200_000
QUICK_N = 10_000
MESSAGE = {"t": 0, "S_VA": [12.5, 431.2, 0.0], "relays": {"P1": True, "P2": False}, "k": 7}


def direct_writer(path: str, n: int) -> float:
    with open(path, "wb") as f:
        writer = Writer(f, chunk_size=128 * 1024, compression=CompressionType.ZSTD)
        writer.start()
        schema = writer.register_schema("m", "jsonschema", b'{"type":"object"}')
        channel = writer.register_channel("/m", "json", schema)
        t0 = time.perf_counter()
        for k in range(n):
            writer.add_message(channel, k, json.dumps(MESSAGE).encode(), k)
        elapsed = time.perf_counter() - t0
        writer.finish()
    return elapsed / n * 1e6


@dataclass(frozen=True)
class Stream:
    """Messages as a lockstep loop logs them: ``per_tick`` at each tick of ``tick_ns``."""

    name: str
    messages: int
    per_tick: int
    tick_ns: int

    @property
    def session_s(self) -> float:
        return self.messages // self.per_tick * self.tick_ns / 1e9


@dataclass(frozen=True)
class RecorderRun:
    log_us: float      # per message, on the loop thread
    rate: float        # messages per second, until the file is finished
    writer_cpu_s: float  # the writer process's CPU time
    written: int
    chunks: int
    file_bytes: int


def children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def hil_recorder(path: str, stream: Stream, chunk_span_s: float | None = 1.0) -> RecorderRun:
    # room for all: nothing dropped
    cpu = children_cpu_s()
    recorder = Recorder(path, max_backlog_bytes=1 << 30, chunk_span_s=chunk_span_s)
    topic = recorder.topic("/m", {"type": "object", "title": "m"})
    n = stream.messages
    t0 = time.perf_counter()
    for k in range(n):
        topic.log(k // stream.per_tick * stream.tick_ns, MESSAGE)
        if k % stream.per_tick == stream.per_tick - 1:
            recorder.flush()  # the loop's hand-over after a tick
    enqueue = time.perf_counter() - t0
    stats = recorder.close()  # the writer process has ended: its CPU time is counted
    total = time.perf_counter() - t0
    cpu = children_cpu_s() - cpu
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    chunks = len(summary.chunk_indexes) if summary is not None else 0
    return RecorderRun(enqueue / n * 1e6, n / total, cpu, stats.messages_written, chunks,
                       os.path.getsize(path))


def bound_and_not(tmp: str, stream: Stream, repeats: int) -> tuple[RecorderRun, RecorderRun]:
    """The median runs (by writer CPU) with the 1 s chunk bound and without, alternated."""
    bounded, unbounded = [], []
    for k in range(repeats):
        bounded.append(hil_recorder(f"{tmp}/bounded-{k}.mcap", stream))
        unbounded.append(hil_recorder(f"{tmp}/unbounded-{k}.mcap", stream, chunk_span_s=None))
    def median(runs: list[RecorderRun]) -> RecorderRun:
        return sorted(runs, key=lambda r: r.writer_cpu_s)[len(runs) // 2]
    return median(bounded), median(unbounded)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--messages", type=int, help=f"messages per run (default {N}; "
                        f"{QUICK_N} with --quick)")
    add_quick(parser)
    args = parser.parse_args()
    n = args.messages or (QUICK_N if args.quick else N)
    repeats = 1 if args.quick else 3
    servo = Stream("servo, 2 kHz", n, 4, 500_000)
    bench = Stream("bench, 100 Hz", 8400, 3, 10_000_000)  # a 28 s machine cycle
    with tempfile.TemporaryDirectory() as tmp:
        base_us = direct_writer(f"{tmp}/direct.mcap", n)
        runs = {stream: bound_and_not(tmp, stream, repeats) for stream in (servo, bench)}
    run = runs[servo][0]
    assert run.written >= n, f"recorder wrote {run.written} of {n}"
    print(f"{'messages':<40} {n} ({servo.session_s:g} s of session time)")
    print(f"{'direct json+mcap on the caller [us/msg]':<40} {base_us:8.2f}   (baseline)")
    print(f"{'hil log + hand-over, loop process [us/msg]':<40} {run.log_us:8.2f}   "
          f"{base_us / run.log_us:.0f}x cheaper than writing directly (target <= 5 us)")
    print(f"{'hil sustained throughput [msg/s]':<40} {run.rate:8.0f}   (target >= 50000)")
    print(f"the 1 s chunk bound (lockstep, median of {repeats}), against chunks closed by size "
          "and wall time only:")
    for stream, (bounded, unbounded) in runs.items():
        label = f"{stream.name}, {stream.messages} msg in {stream.session_s:g} s"
        print(f"  {label:<38} writer CPU {bounded.writer_cpu_s * 1e3:7.1f} ms against "
              f"{unbounded.writer_cpu_s * 1e3:.1f} "
              f"({bounded.writer_cpu_s / unbounded.writer_cpu_s - 1:+.0%}); chunks "
              f"{bounded.chunks} against {unbounded.chunks}; file "
              f"{bounded.file_bytes / unbounded.file_bytes - 1:+.1%}")


if __name__ == "__main__":
    main()
