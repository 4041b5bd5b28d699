"""Recorder cost in the loop process (Topic.log + the per-tick hand-over to the writer
process) and sustained throughput, vs writing directly.

Baseline: what a loop would pay writing each message itself (json.dumps + mcap add_message on
the calling thread). Targets (the project's): <= 5 us per message on the loop thread, >= 50k msg/s.
The hand-over runs every 4 messages here, as a 2 kHz servo tick logs about that many.
``--quick``: 10,000 messages instead of 200,000 (a second or two; figures not worth quoting).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time

from benchkit import add_quick
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


def hil_recorder(path: str, n: int) -> tuple[float, float, int]:
    recorder = Recorder(path, max_backlog_bytes=1 << 30)  # room for all: nothing dropped
    topic = recorder.topic("/m", {"type": "object", "title": "m"})
    t0 = time.perf_counter()
    for k in range(n):
        topic.log(k, MESSAGE)
        if k % 4 == 3:
            recorder.flush()  # the loop's hand-over after a tick
    enqueue = time.perf_counter() - t0
    stats = recorder.close()
    total = time.perf_counter() - t0
    return enqueue / n * 1e6, n / total, stats.messages_written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--messages", type=int, help=f"messages per run (default {N}; "
                        f"{QUICK_N} with --quick)")
    add_quick(parser)
    args = parser.parse_args()
    n = args.messages or (QUICK_N if args.quick else N)
    with tempfile.TemporaryDirectory() as tmp:
        base_us = direct_writer(f"{tmp}/direct.mcap", n)
        log_us, rate, written = hil_recorder(f"{tmp}/hil.mcap", n)
    assert written >= n, f"recorder wrote {written} of {n}"
    print(f"{'messages':<40} {n}")
    print(f"{'direct json+mcap on the caller [us/msg]':<40} {base_us:8.2f}   (baseline)")
    print(f"{'hil log + hand-over, loop process [us/msg]':<40} {log_us:8.2f}   "
          f"{base_us / log_us:.0f}x cheaper than writing directly (target <= 5 us)")
    print(f"{'hil sustained throughput [msg/s]':<40} {rate:8.0f}   (target >= 50000)")


if __name__ == "__main__":
    main()
