"""Session-file size by encoding: bytes per servo tick and per bench day.

One lockstep servo run (PID, default 10 s) and one lockstep bench run (BC, 2 cycles) are
recorded; their messages are then re-recorded with only the topics measured, once as JSON
(the baseline, as every topic was before) and once with the default compact encoding (CDR with
a ros2msg schema), so both figures come from the same messages in the same run. Bytes are
whole-file bytes minus an empty session's, so chunk compression, MCAP record overhead and the
message indexes (16 B per message, which Foxglove's reader requires) are all counted.

Targets: servo /drive/command + /drive/feedback <= 32 B per tick; bench <= 1 GB per 24 h.
``--quick``: a 0.1 s servo run and one bench cycle of a 4 s machining sequence instead of the
28 s one (a few seconds; figures not worth quoting).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

from benchkit import add_quick

from hil.bench.run import BenchRunOptions, run_bench
from hil.core.recording.reader import SessionData, read_session
from hil.core.recording.recorder import Recorder, RecordingOptions
from hil.servo.run import ServoRunOptions, run_servo
from hil.servo.topics import COMMAND_SCHEMA, FEEDBACK_SCHEMA

# --quick: a 4 s machining sequence instead of bench.toml's 28 s one (same devices and topics)
SHORT_SEQUENCE = """[sequence]
period_s = 4.0
stages = [{ start_s = 0.0, end_s = 2.0, on = ["M1"] },
          { start_s = 2.0, end_s = 4.0, on = ["M1", "M2"] }]
"""


def empty_session_bytes(folder: Path) -> int:
    """The bytes of a session with no topic (header, metadata, summary, footer)."""
    empty = folder / "empty.mcap"
    if not empty.exists():
        Recorder(empty).close()
    return os.path.getsize(empty)


def rerecord(data: SessionData, topics: dict[str, dict], path: Path, encoding: str) -> int:
    """Bytes taken by ``topics`` of ``data`` written again with ``encoding``."""
    recorder = Recorder(path, wait_when_full=True)
    handles = {name: recorder.topic(name, schema, encoding=encoding)
               for name, schema in topics.items()}
    merged = sorted((t, name, m) for name in topics for t, m in data.topic(name))
    for t, name, message in merged:
        handles[name].log(t, message)
    recorder.close()
    return os.path.getsize(path) - empty_session_bytes(path.parent)


def bench_schemas(data: SessionData) -> dict[str, dict]:
    """The bench topics' JSON Schemas, rebuilt with their x-cdr hints as the run declares."""
    schemas = {}
    for name in ("/bench/power", "/bench/levels"):  # SDM630 registers: float32 on the wire
        schemas[name] = {"type": "object", "title": name, "properties": {
            f: {"type": "number", "x-cdr": "float32"} for f in data.topic(name)[0][1]}}
    relays = list(data.topic("/bench/relays")[0][1])
    schemas["/bench/relays"] = {"type": "object", "title": "hil.BenchRelays", "properties": {
        f: {"type": "integer", "x-cdr": "uint8"} for f in relays}}
    return schemas


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float,
                        help="servo run [s] (default 10; 0.1 with --quick)")
    parser.add_argument("--cycles", type=int, help="bench run, 28 s each (default 2; one "
                        "4 s cycle with --quick)")
    add_quick(parser)
    args = parser.parse_args()
    args.seconds = args.seconds or (0.1 if args.quick else 10.0)
    args.cycles = args.cycles or (1 if args.quick else 2)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        bench_config = None
        if args.quick:
            bench_config = str(tmp / "short-sequence.toml")
            Path(bench_config).write_text(SHORT_SEQUENCE)
        as_json = RecordingOptions(high_rate_encoding="json")  # the source: full precision
        run_servo(ServoRunOptions(controller="pid", duration_s=args.seconds,
                                 out=str(tmp / "servo.mcap"), recording=as_json))
        servo = read_session(tmp / "servo.mcap")
        ticks = len(servo.topic("/drive/feedback"))
        drive = {"/drive/command": COMMAND_SCHEMA, "/drive/feedback": FEEDBACK_SCHEMA}
        servo_bytes = {enc: rerecord(servo, drive, tmp / f"servo-{enc}.mcap", enc)
                       for enc in ("json", "cdr")}

        run_bench(BenchRunOptions(controller="bc", cycles=args.cycles, config_path=bench_config,
                                  out=str(tmp / "bench-default.mcap")))
        whole = os.path.getsize(tmp / "bench-default.mcap")
        run_bench(BenchRunOptions(controller="bc", cycles=args.cycles, config_path=bench_config,
                                  out=str(tmp / "bench.mcap"), recording=as_json))
        bench = read_session(tmp / "bench.mcap")
        schemas = bench_schemas(bench)
        bench_bytes = {enc: rerecord(bench, schemas, tmp / f"bench-{enc}.mcap", enc)
                       for enc in ("json", "cdr")}
        hours = bench.duration_s() / 3600
    print(f"servo, PID, {args.seconds:g} s lockstep: {ticks} ticks of /drive/command + "
          "/drive/feedback")
    for enc, size in servo_bytes.items():
        print(f"   {enc:<5} {size / ticks:7.1f} B/tick   {size / ticks * 2000 * 86400 / 1e9:6.2f} "
              f"GB/day at 2 kHz{'   (baseline)' if enc == 'json' else ''}")
    print(f"   cdr is {servo_bytes['cdr'] / servo_bytes['json']:.2f}x the JSON size; message "
          "indexes alone are 32 B/tick (2 messages x 16 B)")
    print(f"bench, BC, {args.cycles} cycles of {4 if args.quick else 28} s lockstep: "
          "/bench/power + /bench/levels + /bench/relays at 100 Hz")
    for enc, size in bench_bytes.items():
        print(f"   {enc:<5} {size / hours / 1e6:7.1f} MB/h  {size / hours * 24 / 1e9:6.2f} GB/day"
              f"{'   (baseline)' if enc == 'json' else ''}")
    print(f"   whole session file as recorded (every topic, defaults): "
          f"{whole / hours * 24 / 1e9:.2f} GB/day")
    print("targets")
    per_tick = servo_bytes["cdr"] / ticks
    per_day = whole / hours * 24 / 1e9
    print(f"   servo <= 32 B/tick ({per_tick:.1f}): {'met' if per_tick <= 32 else 'MISSED'}")
    print(f"   bench <= 1 GB/day ({per_day:.2f}): {'met' if per_day <= 1 else 'MISSED'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
