"""Tuning while it runs: what a client changing a gain 10 times per second costs a real-time
loop, next to the same session with the live view and no tuning, in the same run.

Each session is ``hil servo run --controller pid --realtime --live PORT`` (2 kHz, the drive
emulator in a process of its own) in a process of its own. Three kinds of runs alternate
(baseline, tuned, pushed, baseline...) so that drift in the shared machine's load hits all:

* baseline: the live view on, one client connected that sets nothing;
* tuned: a client (a process of its own, on the `websockets` package, as Foxglove would be)
  that sets ``controller.kp`` ``--rate`` times per second, alternating between 4.0 and its
  value, each set waiting for its answer (applied at a tick boundary); nobody subscribed to
  parameter updates;
* pushed: the same, with ``--subscribers`` more connections subscribed to ``controller.kp``
  (``subscribeParameterUpdates``, as Foxglove's Parameters panel does), each sent every change:
  pushing parameter updates against not pushing them, in the same run.

Then one MPC run whose client changes the prediction horizon H_p (50 <-> 40 ticks, rebuilt
off the loop) ``--rebuild-rate`` times per second.

Printed per run: the loop's skipped ticks and lateness p99, the sets answered, refused and
their round trip (client to applied and back), and the set-to-effect latency in ticks (the
recorded ``param.changed`` events: ``tick`` - ``asked_at_tick``), and the updates each
subscriber received. Then the skipped share of the tuned PID runs against the baseline's
(``ratio``), and of the pushed runs against the tuned ones (what pushing costs the loop).
The watchdogs are kept off the machine's CAN timing (a late TPDO is counted, a late heartbeat
does not fault the drive), as in benchmarks/live.py. ``--quick``: the 0.5 s MPC run alone,
with the pushed runs' subscribers (its client sets H_p as a tuned run's sets K_pos; the
baseline, tuned and pushed runs skipped; seconds; figures not worth quoting).
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import tomli_w

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchkit import add_quick, fill_defaults

from hil.core.config import deep_merge
from hil.core.recording.reader import read_session
from hil.servo.config import drive_for

REPO = Path(__file__).resolve().parents[1]
TOLERANT = {"master": {"stale_cycles": 100_000, "heartbeat_timeout_ms": 0},
            "safety": {"stale_share_max": 1.0}}
PARAMETER = "controller.kp"
KP_OTHER = 4.0           # rpm/deg: the PID's K_pos is 3.61 by default
REBUILT = "controller.hp"
HP_OTHER = 40            # ticks: the MPC's H_p is 50 by default

CLIENT = """
import json, sys, time
from tests.live.foxglove_client import FoxgloveClient
port, rate, name, other = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3], json.loads(sys.argv[4])
subscribers = int(sys.argv[5])
client = FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=120)
client.wait_for(lambda: bool(client.server_info), 60)
base = client.get_parameters([name], "base")[name]["value"] if rate else None
watchers = [FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=120) for _ in range(subscribers)]
for watcher in watchers:
    watcher.subscribe_parameter_updates([name])
    watcher.get_parameters([name], "sync")  # its subscription is in place


def drain():
    for watcher in watchers:
        while not watcher.closed and watcher.pump(0.0):
            pass


print("ready", flush=True)
sets, refused, round_trips, n = 0, 0, [], 0
next_at = time.monotonic()
while not client.closed:
    if not rate:
        client.pump(1.0)
        continue
    next_at += 1 / rate
    value = other if n % 2 == 0 else base
    request_id, n = f"s{n}", n + 1
    start = time.monotonic()
    client.ws.send(json.dumps({"op": "setParameters", "id": request_id,
                               "parameters": [{"name": name, "value": value}]}))
    if not client.wait_for(lambda: request_id in client.answers, 10):
        break
    round_trips.append(time.monotonic() - start)
    answer = {p["name"]: p["value"] for p in client.answers[request_id]}
    sets += 1
    refused += answer.get(name) != value
    drain()
    while not client.closed and time.monotonic() < next_at:
        client.pump(max(0.0, next_at - time.monotonic()))
drain()
round_trips.sort()
print(json.dumps({"sets": sets, "refused": refused,
                  "pushed": [len(watcher.updates) for watcher in watchers],
                  "p50_ms": 1e3 * round_trips[len(round_trips) // 2] if round_trips else 0,
                  "max_ms": 1e3 * round_trips[-1] if round_trips else 0}), flush=True)
"""


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def run_once(tmp: str, name: str, duration_s: float, rate_hz: float, controller: str = "pid",
             parameter: str = PARAMETER, other: float = KP_OTHER, subscribers: int = 0
             ) -> dict[str, Any]:
    """One real-time session with its client (setting ``parameter`` to ``other`` and back at
    ``rate_hz``, or only watching) and ``subscribers`` connections subscribed to it."""
    port, out = _free_port(), f"{tmp}/{name}.mcap"
    config = Path(tmp) / f"{name}.toml"
    config.write_bytes(tomli_w.dumps(deep_merge(drive_for(12000.0), TOLERANT)).encode())
    run = subprocess.Popen(
        [sys.executable, "-m", "hil", "servo", "run", "--controller", controller, "--realtime",
         "--duration", str(duration_s), "--config", str(config), "--out", out, "--json",
         "--quiet", "--live", str(port)],
        cwd=tmp, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    client = subprocess.Popen([sys.executable, "-c", CLIENT, str(port), str(rate_hz),
                               parameter, json.dumps(other), str(subscribers)], cwd=REPO,
                              stdout=subprocess.PIPE, text=True)
    stdout, stderr = run.communicate()
    tuned, _ = client.communicate(timeout=60)
    lines = [line for line in tuned.splitlines() if line.startswith("{")]
    session = read_session(out)
    loop = json.loads(session.metadata.get("loop", {}).get("servo", "{}"))
    latencies = sorted(event["data"]["tick"] - event["data"]["asked_at_tick"]
                       for _, event in session.topic("/events")
                       if event["kind"] == "param.changed")
    return {"loop": loop, "kpis": json.loads(stdout) if stdout.strip() else {},
            "latency_ticks": latencies,
            "client": json.loads(lines[-1]) if lines else {},
            "error": stderr.strip().splitlines()[-1:] if run.returncode not in (0, 3) else []}


def skipped_share(rows: list[dict[str, Any]]) -> float:
    """Skipped ticks over scheduled ones, of all ``rows`` together [%]."""
    missed = sum(r["loop"].get("missed", 0) for r in rows)
    total = sum(r["loop"].get("runs", 0) + r["loop"].get("missed", 0) for r in rows)
    return 100 * missed / max(1, total)


def print_run(label: str, row: dict[str, Any]) -> None:
    loop, client = row["loop"], row["client"]
    print(f"{label}: skipped {loop.get('missed', 0)} ({skipped_share([row]):.3f} %), lateness "
          f"p99 {loop.get('lateness_us', {}).get('p99', 0):.1f} us; ended: "
          f"{row['kpis'].get('stop_reason', 'no KPIs')} {' '.join(row['error'])}")
    if client.get("sets"):
        print(f"   {client['sets']} sets answered, {client['refused']} refused, round trip "
              f"p50 {client['p50_ms']:.1f} ms, max {client['max_ms']:.1f} ms")
    if client.get("pushed"):
        print(f"   updates received by each subscriber: "
              f"{', '.join(map(str, client['pushed']))}")
    latencies = row["latency_ticks"]
    if latencies:
        print(f"   set to effect: {len(latencies)} changes, p50 "
              f"{latencies[len(latencies) // 2]} ticks, max {latencies[-1]} ticks")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, help="seconds per run (default 10)")
    parser.add_argument("--pairs", type=int, help="baseline/tuned pairs (default 3)")
    parser.add_argument("--rate", type=float, default=10.0, metavar="HZ",
                        help="the tuning client's sets per second (default 10)")
    parser.add_argument("--rebuild-rate", type=float, default=2.0, metavar="HZ",
                        help="the MPC run's H_p changes per second (default 2)")
    parser.add_argument("--subscribers", type=int, default=2, metavar="N",
                        help="connections subscribed to the tuned parameter in the pushed runs "
                        "(default 2)")
    add_quick(parser)
    args = parser.parse_args()
    fill_defaults(args, {"duration": (10.0, 0.5), "pairs": (3, 1)})
    print(f"real-time servo, PID at 2 kHz, --live, {args.duration:g} s per run, {args.pairs} "
          f"round(s), alternating: a client watching / a client setting {PARAMETER} "
          f"{args.rate:g} times per second / the same with {args.subscribers} subscriber(s) "
          "sent every change")
    kinds = () if args.quick else ("baseline", "tuned", "pushed")
    rows: dict[str, list[dict[str, Any]]] = {kind: [] for kind in kinds}
    with tempfile.TemporaryDirectory() as tmp:
        for pair in range(args.pairs):
            for kind in kinds:
                row = run_once(tmp, f"r{pair}{kind}", args.duration,
                               0.0 if kind == "baseline" else args.rate,
                               subscribers=args.subscribers if kind == "pushed" else 0)
                rows[kind].append(row)
                print_run(f"{kind} #{pair + 1}", row)
        watchers = args.subscribers if args.quick else 0  # --quick: the pushed runs' path
        rebuilt = run_once(tmp, "mpc", args.duration, args.rebuild_rate, "mpc", REBUILT,
                           HP_OTHER, subscribers=watchers)
        print_run(f"MPC, {REBUILT} changed {args.rebuild_rate:g} times per second "
                  f"(rebuilt off the loop), {watchers} subscriber(s)", rebuilt)
    if args.quick:
        print(f"skipped share: MPC {skipped_share([rebuilt]):.3f} % (baseline, tuned and "
              "pushed runs skipped: --quick)")
        return
    tuned, pushed = skipped_share(rows["tuned"]), skipped_share(rows["pushed"])
    print(f"skipped share: tuned {tuned:.3f} %, pushed {pushed:.3f} % "
          f"(pushing: {_ratio(pushed, tuned):.2f}x)")
    base = skipped_share(rows["baseline"])
    print(f"skipped share: baseline {base:.3f} %, tuned {tuned:.3f} %, ratio "
          f"{_ratio(tuned, base):.2f}x")


def _ratio(share: float, against: float) -> float:
    return share / against if against else float("inf") if share else 1.0


if __name__ == "__main__":
    main()
