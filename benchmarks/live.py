"""Live view cost: real-time servo sessions with ``--live`` and clients, next
to the same session without the live view, in the same run.

Each session is ``hil servo run --controller mpc --realtime`` (MPC FOH at 2 kHz, the drive
emulator in a process of its own, as ``--realtime`` starts it) in a process of its own, while
this process watches it from ``/proc``. Two kinds of clients, each in a process of its own on
the `websockets` package, as Foxglove would be:

* default: one client subscribed to every topic for the whole run;
* ``--churn N``: N clients that connect, subscribe to everything, read for ``--hold`` seconds
  and disconnect, over and over (browser tabs coming and going);
* ``--stalled``: one client that subscribes to the busiest topics, served at every message,
  and then never reads (a browser tab frozen in the background): its queue in the server
  overflows, and the session's skipped ticks beside the run without the live view say whether
  it slowed the loop.

The runs alternate (off, on, off, on...) so that drift in the shared machine's load hits both.
Printed per run: the loop's lateness p50/p99/max and skipped ticks, the stale feedback and the
side that was late (``hil report``'s feedback section), how the run ended, and where the CPU
went: the loop process, the drive emulator (with the time it waited for a CPU), the writer
split into the recording (its Python thread) and the live server (the SDK's threads), and the
clients. The default runs keep the watchdogs off the machine's CAN timing (a late TPDO is
counted, a late heartbeat does not fault the drive); ``--churn`` runs as shipped, safety net
and watchdogs on, so that whether they complete is part of the figures. ``--quick``: one 0.3 s run
with the live view, the one without it (the baseline) skipped (seconds; figures not worth
quoting).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

import tomli_w

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchkit import add_quick

from hil.core.config import deep_merge
from hil.core.recording.reader import read_session
from hil.servo.config import drive_for
from hil.servo.report import FEEDBACK_TIMING

REPO = Path(__file__).resolve().parents[1]
TOLERANT = {"master": {"stale_cycles": 100_000, "heartbeat_timeout_ms": 0},
            "safety": {"stale_share_max": 1.0}}
TICKS_PER_S = os.sysconf("SC_CLK_TCK")
LIVE_SERVER_THREADS = ("tokio-rt-worker",)  # the Foxglove SDK's server runtime
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

CHURN = """
import sys, threading, time
from tests.live.foxglove_client import FoxgloveClient
url, clients, hold = f"ws://127.0.0.1:{sys.argv[1]}", int(sys.argv[2]), float(sys.argv[3])
done, failed, messages = [0], [0], [0]

def come_and_go():
    while True:
        try:
            client = FoxgloveClient(url, 120)
            client.wait_for(lambda: bool(client.topics()), 10)
            client.subscribe(sorted(client.topics()))
            until = time.monotonic() + hold
            while time.monotonic() < until and client.pump(0.05):
                pass
            messages[0] += sum(len(m) for m in client.messages.values())
            client.close()
            done[0] += 1
        except Exception:
            failed[0] += 1
            time.sleep(0.1)

for _ in range(clients):
    threading.Thread(target=come_and_go, daemon=True).start()
sys.stdin.read()  # until the benchmark closes it
print(f"{done[0]} {failed[0]} {messages[0]}", flush=True)
"""

STALLED_TOPICS = (
    "/drive/command", "/drive/feedback", "/loop/servo/timing", "/mpc/prediction")
STALLED = f"""
import sys
from tests.live.foxglove_client import stalled_client
sock = stalled_client("127.0.0.1", int(sys.argv[1]), {list(STALLED_TOPICS)!r}, 120)
sys.stdin.read()  # until the benchmark closes it
sock.close()
print("stalled")
"""


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class ProcessCpu:
    """CPU time and run-queue wait [s] of every thread of a process tree from the start of
    the session (its writer process appears: the emulator is up and hardened, the start-up's
    imports are over) to :meth:`stop`, sampled from /proc by a thread of this process."""

    def __init__(self, roots: list[int]) -> None:
        self.roots = roots
        self.threads: dict[tuple[int, int], tuple[str, str, float, float]] = {}
        self.before: dict[tuple[int, int], tuple[float, float]] = {}  # at the session's start
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def stop(self) -> dict[str, dict[str, float]]:
        """``{process role: {"cpu_s", "wait_s"}}``; the writer split into ``recording`` and
        ``live server``."""
        self._stop.set()
        self._thread.join()
        roles: dict[str, dict[str, float]] = {}
        for key, (role, comm, cpu, wait) in self.threads.items():
            cpu_before, wait_before = self.before.get(key, (0.0, 0.0))
            cpu, wait = cpu - cpu_before, wait - wait_before
            if role == "writer":
                role = "writer: live server" if comm in LIVE_SERVER_THREADS else \
                    "writer: recording"
            row = roles.setdefault(role, {"cpu_s": 0.0, "wait_s": 0.0})
            row["cpu_s"] += cpu
            row["wait_s"] += wait
        return roles

    def _sample(self) -> None:
        while not self._stop.wait(0.2):
            started = bool(self.before)
            for pid in self._tree():
                role = _role(pid)
                for tid, comm, cpu, wait in _threads(pid):
                    self.threads[(pid, tid)] = (role, comm, cpu, wait)
            if not started and any(role == "writer" for role, *_ in self.threads.values()):
                self.before = {key: (cpu, wait) for key, (_, _, cpu, wait)
                               in self.threads.items()}

    def _tree(self) -> list[int]:
        found, todo = [], list(self.roots)
        while todo:
            pid = todo.pop()
            found.append(pid)
            todo += _children(pid)
        return found


def _read(path: str) -> str:
    try:
        return Path(path).read_text()
    except OSError:
        return ""


def _children(pid: int) -> list[int]:
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return []
    return [int(c) for t in tasks for c in _read(f"/proc/{pid}/task/{t}/children").split()]


def _role(pid: int) -> str:
    if _read(f"/proc/{pid}/comm").strip() == "hil writer":  # forked: the server's command line
        return "writer"
    command = _read(f"/proc/{pid}/cmdline").replace("\0", " ")
    for needle, role in (("hil.core.recording.writer_fork", "writer fork server"),
                         ("emulate drive", "drive emulator"),
                         ("servo run", "loop process"), ("foxglove_client", "clients")):
        if needle in command:
            return role
    return "other"


def _threads(pid: int) -> list[tuple[int, str, float, float]]:
    rows: list[tuple[int, str, float, float]] = []
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return rows
    for tid in tids:
        base = f"/proc/{pid}/task/{tid}"
        stat, sched = _read(f"{base}/stat"), _read(f"{base}/schedstat").split()
        if not stat or len(sched) < 2:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        cpu = (int(fields[11]) + int(fields[12])) / TICKS_PER_S
        rows.append((int(tid), _read(f"{base}/comm").strip(), cpu, int(sched[1]) / 1e9))
    return rows


def run_once(tmp: str, name: str, duration_s: float, live: bool, churn: int,
             hold_s: float, stalled: bool = False) -> dict[str, Any]:
    """One real-time session in a process of its own, with its clients if ``live``."""
    port, out = _free_port(), f"{tmp}/{name}.mcap"
    drive = drive_for(12000.0) if churn else deep_merge(drive_for(12000.0), TOLERANT)
    config = Path(tmp) / f"{name}.toml"
    config.write_bytes(tomli_w.dumps(drive).encode())
    run = subprocess.Popen(
        [sys.executable, "-m", "hil", "servo", "run", "--controller", "mpc", "--realtime",
         "--reference", "sine:amplitude=2,frequency=10", "--duration", str(duration_s),
         "--config", str(config), "--out", out, "--json", "--quiet",
         *(["--live", str(port)] if live else []),
         # a stalled client is served every message, so that its queue overflows
         *([f"--live-rate={topic}=0" for topic in STALLED_TOPICS] if live and stalled else [])],
        cwd=tmp, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    clients = None
    if live:
        script, args = (CHURN, [str(churn), str(hold_s)]) if churn else \
            (STALLED, []) if stalled else (WATCHER, [])
        clients = subprocess.Popen([sys.executable, "-c", script, str(port), *args], cwd=REPO,
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    cpu = ProcessCpu([run.pid, *([clients.pid] if clients else [])])
    stdout, stderr = run.communicate()
    received = "-"
    if clients is not None:
        if churn or stalled:
            received, _ = clients.communicate("", timeout=60)
        else:
            received, _ = clients.communicate(timeout=60)
        received = received.strip() or "none"
    roles = cpu.stop()
    kpis = json.loads(stdout) if stdout.strip() else {}
    session = read_session(out)
    loop = json.loads(session.metadata.get("loop", {}).get("servo", "{}"))
    feedback = FEEDBACK_TIMING.section(session).get("/drive/feedback", {})
    live_meta = session.metadata.get("live", {})
    return {"loop": loop, "kpis": kpis, "feedback": feedback, "cpu": roles,
            "received": received, "queue_full": live_meta.get("client_queue_full", "-"),
            "error": stderr.strip().splitlines()[-1:] if run.returncode not in (0, 3) else []}


def print_run(label: str, row: dict[str, Any], churn: int) -> None:
    loop, feedback = row["loop"], row["feedback"]
    lateness = loop.get("lateness_us", {})
    runs, missed = loop.get("runs", 0), loop.get("missed", 0)
    print(f"{label}: loop lateness p50/p99/max {lateness.get('p50', 0):.1f}/"
          f"{lateness.get('p99', 0):.1f}/{lateness.get('max', 0):.1f} us, skipped {missed} "
          f"({100 * missed / max(1, runs + missed):.3f} %); ended: "
          f"{row['kpis'].get('stop_reason', 'no KPIs')} {' '.join(row['error'])}")
    if feedback:
        print(f"   stale feedback {feedback['stale']} of {feedback['cycles']} "
              f"({100 * feedback['stale_share']:.2f} %), late side {feedback['late_side']}, "
              f"worst {feedback['worst_window']['window_ms']:g} ms window "
              f"{feedback['worst_window']['stale']} of {feedback['worst_window']['cycles']}")
    if churn and row["received"] != "-":
        done, failed, messages = row["received"].split()
        print(f"   clients: {done} connections done, {failed} failed, {messages} messages")
    elif row["received"] == "stalled":
        print(f"   client: stalled, its queue overflowed {row['queue_full']} time(s)")
    elif row["received"] != "-":
        print(f"   client: {row['received']} messages")
    print("   CPU [s]: " + ", ".join(
        f"{role} {v['cpu_s']:.2f} (waited {v['wait_s']:.2f})"
        for role, v in sorted(row["cpu"].items())))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float,
                        help="seconds per run (default 10; 0.3 with --quick)")
    parser.add_argument("--pairs", type=int, help="off/on pairs (default 2; 1 with --quick)")
    parser.add_argument("--churn", type=int, default=0, metavar="N",
                        help="N clients coming and going instead of one watching throughout")
    parser.add_argument("--hold", type=float, default=0.3, metavar="S",
                        help="with --churn: seconds each connection reads before it closes")
    parser.add_argument("--stalled", action="store_true",
                        help="one client that subscribes and never reads instead of one watching")
    add_quick(parser)
    args = parser.parse_args()
    args.duration = args.duration or (0.3 if args.quick else 10.0)
    args.pairs = args.pairs or (1 if args.quick else 2)
    if args.churn and args.stalled:
        parser.error("--churn and --stalled are two kinds of client: choose one")
    clients = f"{args.churn} clients coming and going" if args.churn else \
        "1 stalled client" if args.stalled else "1 client"
    print(f"real-time servo, MPC FOH H_t = H_u = 8 at 2 kHz, {args.duration:g} s per run, "
          + (f"--live + {clients} only (--quick)" if args.quick else
             f"{args.pairs} pair(s), alternating: no live view / --live + {clients}"))
    rows: dict[bool, list[dict[str, Any]]] = {False: [], True: []}
    with tempfile.TemporaryDirectory() as tmp:
        for pair in range(args.pairs):
            for live in (True,) if args.quick else (False, True):
                row = run_once(tmp, f"r{pair}{int(live)}", args.duration, live, args.churn,
                               args.hold, args.stalled)
                rows[live].append(row)
                print_run(f"{'--live + ' + clients if live else 'no live view'} #{pair + 1}",
                          row, args.churn)
    for live in (False, True):
        runs = rows[live]
        if not runs:
            print("mean without the live view: skipped (--quick)")
            continue
        p99 = sum(r["loop"].get("lateness_us", {}).get("p99", 0) for r in runs) / len(runs)
        total = sum(r["loop"].get("runs", 0) + r["loop"].get("missed", 0) for r in runs)
        skipped = 100 * sum(r["loop"].get("missed", 0) for r in runs) / max(1, total)
        stale = sum(r["feedback"].get("stale", 0) for r in runs)
        cycles = sum(r["feedback"].get("cycles", 0) for r in runs)
        print(f"mean {'with' if live else 'without'} the live view: lateness p99 {p99:.1f} us, "
              f"skipped {skipped:.3f} %, stale feedback {100 * stale / max(1, cycles):.3f} %")


if __name__ == "__main__":
    main()
