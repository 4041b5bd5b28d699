"""The cycle's cost over EtherCAT against CAN, in the same run, lockstep and real time.

The same ``hil servo run`` (PID, the default sine, one axis) against hil's drive emulator in a
process of its own, as hardware would be:

* CAN: ``hil emulate drive --socketcand`` on loopback, ``--drive socketcand://...``;
* EtherCAT: ``hil emulate drive --ethercat`` on one end of a veth pair in a network namespace
  made for the run, ``--drive ethercat://OTHER-END?slave=1`` from inside it (root: without it
  the EtherCAT rows say why they are missing).

Lockstep (``--duration`` s, repeated ``--repeat`` times, the transports alternated): the wall
time per cycle (the whole loop: read, compute, write, record, and the wire) and the read
phase (a cycle's answer: TPDOs by SYNC on CAN, the LRW's working counter and inputs on
EtherCAT), median of the runs; the KPIs must be the same over both. Real time at 2 kHz
(``--realtime-s`` s each): stale cycles (CAN: TPDOs not back in time; EtherCAT: a wrong or
missing working counter), the loop's lateness and read phase p99. The machine is shared: the
figures are noisy, run it alone when they matter. ``--quick``: 0.1 s runs, one repeat, 0.2 s
real time (seconds; figures not worth quoting).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import select
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

from benchkit import add_quick, fill_defaults

from hil.cli.output import json_text
from hil.core.recording.reader import read_session
from hil.core.report import summarize
from hil.emulators.ethercat import veth

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
SAME_KPIS = ("max_error_deg", "rms_error_deg", "peak_current_mA", "ticks")


@contextlib.contextmanager
def emulator(prefix: list[str], *args: str) -> Iterator[str]:
    """``hil emulate drive ARGS`` (run under ``prefix``) until the block ends; its ready line."""
    proc = subprocess.Popen([*prefix, sys.executable, "-m", "hil", "emulate", "drive", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            env=ENV)
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], 60)
        line = proc.stdout.readline() if ready else ""
        if not line.startswith("hil: drive emulator"):
            raise SystemExit(f"the drive emulator did not start: {line!r}")
        yield line
    finally:
        proc.terminate()
        proc.communicate(timeout=20)


def servo_run(prefix: list[str], url: str, seconds: float, folder: Path, realtime: bool
              ) -> tuple[dict, dict]:
    """One run (a process, as the drive's host would run it): its KPIs and its loop timing
    (``hil report --json``'s summary, read in this process)."""
    out = folder / f"run-{len(list(folder.iterdir()))}.mcap"
    args = ["servo", "run", "--drive", url, "--controller", "pid", "--duration", str(seconds),
            "--json", "--out", str(out), *(["--realtime"] if realtime else [])]
    done = subprocess.run([*prefix, sys.executable, "-m", "hil", *args], capture_output=True,
                          text=True, env=ENV, cwd=folder, timeout=600)
    lost = done.returncode == 2 and "link lost" in done.stderr and out.exists()
    if done.returncode not in (0, 3) and not lost:  # a loaded machine may lose a real-time link
        raise SystemExit(f"hil {' '.join(args)} exited {done.returncode}: {done.stderr}")
    report = json.loads(json_text(summarize(read_session(out))))  # `hil report --json`'s
    kpis = report["kpis"] if lost else json.loads(done.stdout)
    return {**kpis, "lost": lost}, report["loop"]["servo"]


def transports(pair: veth.Veth | None) -> Iterator[tuple[str, list[str], list[str], str]]:
    """(name, prefix, emulator flags, URL pattern) of each transport measured."""
    yield "CAN (socketcand)", [], ["--socketcand", "127.0.0.1:0"], "socketcand://{}"
    if pair is not None:
        yield ("EtherCAT (veth)", pair.command(), ["--ethercat", pair.slave],
               f"ethercat://{pair.master}?slave=1")


def measure(pair: veth.Veth | None, args: argparse.Namespace) -> None:
    rows: dict[str, dict[str, list[float]]] = {}
    kpis: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for _ in range(args.repeat):
            for name, prefix, flags, pattern in transports(pair):
                with emulator(prefix, *flags) as line:
                    found = re.search(r"socketcand ([\d.]+:\d+)", line)
                    url = pattern.format(found[1]) if found else pattern
                    lock, loop = servo_run(prefix, url, args.duration, folder, False)
                    real, real_loop = servo_run(prefix, url, args.realtime_s, folder, True)
                row = rows.setdefault(name, {})
                row.setdefault("wall_us", []).append(lock["wall_s"] / lock["ticks"] * 1e6)
                row.setdefault("read_us", []).append(loop["read_us"]["p50"])
                row.setdefault("stale_pct", []).append(
                    100 * real["stale_feedback"] / max(real["ticks"], 1))
                row.setdefault("late_p99", []).append(real_loop["lateness_us"]["p99"])
                row.setdefault("rt_read_p99", []).append(real_loop["read_us"]["p99"])
                row.setdefault("lost", []).append(real["lost"])
                kpis[name] = {key: lock[key] for key in SAME_KPIS}
    print(f"lockstep, {args.duration:g} s runs (median of {args.repeat}); real time 2 kHz, "
          f"{args.realtime_s:g} s")
    print(f"{'transport':<18} {'wall/cycle us':>13} {'read p50 us':>11} {'RT stale %':>10} "
          f"{'RT late p99 us':>14} {'RT read p99 us':>14} {'RT link lost':>12}")
    for name, row in rows.items():
        med = {key: statistics.median(values) for key, values in row.items() if key != "lost"}
        print(f"{name:<18} {med['wall_us']:>13.1f} {med['read_us']:>11.1f} "
              f"{med['stale_pct']:>10.2f} {med['late_p99']:>14.1f} {med['rt_read_p99']:>14.1f} "
              f"{sum(row['lost']):>5} of {len(row['lost'])}")
    if len(kpis) == 2:
        can, ethercat = kpis.values()
        print(f"same KPIs in lockstep over both: {'yes' if can == ethercat else 'NO'} "
              f"(max error {ethercat['max_error_deg']:.4f} deg over EtherCAT, "
              f"{can['max_error_deg']:.4f} deg over CAN)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, help="lockstep run length [s] (default 2)")
    parser.add_argument("--repeat", type=int, help="runs of each transport (default 3)")
    parser.add_argument("--realtime-s", type=float, help="real-time run length [s] "
                        "(default 3)")
    add_quick(parser)
    args = parser.parse_args()
    fill_defaults(args, {"duration": (2.0, 0.1), "repeat": (3, 1), "realtime_s": (3.0, 0.2)})
    reason = veth.missing()
    if reason is not None:
        print(f"EtherCAT rows left out: {reason}")
        measure(None, args)
        return
    with veth.veth_pair("hil-bench") as pair:
        measure(pair, args)


if __name__ == "__main__":
    main()
