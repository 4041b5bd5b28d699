"""Live view cost (issue 16): a real-time servo session with ``--live`` and one connected
Foxglove client, next to the same session without the live view, in the same run.

Each pair runs MPC FOH H_t = H_u = 8 on the emulated drive at 2 kHz in real time, recording as
usual; the "live" run also serves every topic over WebSocket (defaults: 100 Hz per topic) to a
real client subscribed to all of them (the `websockets` package, in its own process, as
Foxglove would be). The runs alternate (off, on, off, on...) so that drift in the shared
machine's load hits both. Printed: the loop's lateness p50/p99/max, skipped ticks and their
share, and what the client received. The live view runs in the writer process: the loop figures
should match within noise. A late TPDO counts as stale feedback, and a late master heartbeat
does not fault the drive, instead of ending the run (the figures of interest are the loop's,
not this shared machine's CAN timing).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.core.config import deep_merge
from hil.core.recorder import RecordingOptions
from hil.servo.demo import drive_for
from hil.servo.run import ServoRunOptions, run_servo

REPO = Path(__file__).resolve().parents[1]

TOLERANT = {"master": {"stale_cycles": 100_000, "heartbeat_timeout_ms": 0}}


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


WATCHER = """
import sys
from tests.live.foxglove_client import FoxgloveClient
client = FoxgloveClient(f"ws://127.0.0.1:{sys.argv[1]}", timeout_s=120)
topics = {"/drive/command", "/drive/feedback", "/loop/servo/timing", "/events"}
client.wait_for(lambda: topics <= set(client.topics()), 60)
client.subscribe(sorted(client.topics()))
client.wait_for(lambda: client.closed, 3600)
print(sum(len(m) for m in client.messages.values()))
"""


def run_once(tmp: str, name: str, duration_s: float, live: bool) -> dict[str, Any]:
    """One real-time session; with ``live``, a client process watches it."""
    port = _free_port()
    watcher = None
    if live:
        watcher = subprocess.Popen([sys.executable, "-c", WATCHER, str(port)], cwd=REPO,
                                   stdout=subprocess.PIPE, text=True)
    config = ServoRunOptions(
        controller="mpc", out=f"{tmp}/{name}.mcap", duration_s=duration_s, realtime=True,
        reference="sine:amplitude=2,frequency=10",
        drive_overrides=deep_merge(drive_for(12000.0), TOLERANT),
        recording=RecordingOptions(live=f"127.0.0.1:{port}" if live else None))
    result = run_servo(config)
    received = "-"
    if watcher is not None:
        out, _ = watcher.communicate(timeout=60)
        received = out.strip() or "none"
    stats = result.loop["servo"]
    total = stats["runs"] + stats["missed"]
    return {"lateness": stats["lateness_us"], "missed": stats["missed"], "total": total,
            "received": received}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per run")
    parser.add_argument("--pairs", type=int, default=2, help="off/on pairs")
    args = parser.parse_args()
    print(f"real-time servo, MPC FOH H_t = H_u = 8 at 2 kHz, {args.duration:g} s per run, "
          f"{args.pairs} pair(s), alternating")
    rows: dict[bool, list[dict[str, Any]]] = {False: [], True: []}
    with tempfile.TemporaryDirectory() as tmp:
        for pair in range(args.pairs):
            for live in (False, True):
                rows[live].append(run_once(tmp, f"r{pair}{int(live)}", args.duration, live))
    print(f"{'run':<34}{'lateness p50 us':>16}{'p99 us':>9}{'max us':>10}{'skipped':>9}"
          f"{'skipped %':>10}{'client msgs':>12}")
    for live in (False, True):
        for i, row in enumerate(rows[live]):
            lat = row["lateness"]
            label = f"{'--live + 1 client' if live else 'no live view (baseline)'} #{i + 1}"
            got = row["received"]
            print(f"{label:<34}{lat['p50']:>16.1f}{lat['p99']:>9.1f}{lat['max']:>10.1f}"
                  f"{row['missed']:>9}{100 * row['missed'] / row['total']:>10.3f}{got:>12}")
    for live in (False, True):
        runs = rows[live]
        p99 = sum(r["lateness"]["p99"] for r in runs) / len(runs)
        skipped = 100 * sum(r["missed"] for r in runs) / sum(r["total"] for r in runs)
        rows[live] = [{"p99": p99, "skipped": skipped}]
    off, on = rows[False][0], rows[True][0]
    print(f"mean of runs: lateness p99 {off['p99']:.1f} us without, {on['p99']:.1f} us with "
          f"(ratio {on['p99'] / off['p99'] if off['p99'] else float('inf'):.2f}); skipped "
          f"{off['skipped']:.3f} % without, {on['skipped']:.3f} % with")


if __name__ == "__main__":
    main()
