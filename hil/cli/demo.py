"""``hil demo``: EEC vs BC and MPC vs PID against the built-in emulators.

Each half is a function that runs its sessions into the output folder and returns the text
it prints; :func:`demo_command` prints the halves one after the other.
"""

from __future__ import annotations

import argparse
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from hil.cli.output import add_quiet_argument
from hil.cli.recording import add_live_arguments, live_address
from hil.core.recording.recording_options import RecordingOptions

BENCH_COLUMNS = ("J1_VA", "J2_VA", "SEC_VA", "peak_VA", "overlap_s", "dwell_violations",
                 "level_violations")


def register(subparsers: argparse._SubParsersAction) -> None:
    demo = subparsers.add_parser(
        "demo", help="EEC vs BC on the emulated bench, MPC vs PID on the emulated drive",
        description="The embedded default experiment against the built-in emulators (lockstep): "
        "bench over Modbus TCP on loopback, EEC vs BC for 8 machine cycles; drive over CAN, MPC "
        "vs PID on a 2 deg sine. Writes MCAP files and PNG reports, prints comparison tables.",
    )
    demo.add_argument("--out", default="sessions", metavar="DIR",
                      help="output folder (default: sessions, where every run records)")
    add_quiet_argument(demo, "no progress lines on stderr (which half runs now) and no "
                       "runs' progress lines")
    add_live_arguments(demo)
    demo.set_defaults(handler=demo_command)


def live_ports(args: argparse.Namespace) -> tuple[str | None, str | None]:
    """``--live HOST:PORT`` of the demo: the EEC session and the servo sessions (one after the
    other: Foxglove reconnects) on PORT, the BC session (beside the EEC's) on PORT + 1."""
    address = live_address(args)
    if address is None or args.live[1] == 0:
        return address, address
    host, port = args.live
    args.live = (host, port + 1)
    return address, live_address(args)


def demo_command(args: argparse.Namespace) -> int:
    from hil.servo.demo import format_servo_demo, run_servo_demo

    os.makedirs(args.out, exist_ok=True)
    first, second = live_ports(args)
    live = {"live_rates": dict(args.live_rate), "live_remote_tuning": args.allow_remote_tuning}
    say = (lambda message: None) if args.quiet else progress
    say("relay bench: EEC vs BC, 8 machine cycles over Modbus TCP (lockstep, ~30 s)")
    print(bench_demo(args.out, {"eec": RecordingOptions(live=first, **live),
                                "bc": RecordingOptions(live=second, **live)}, args.quiet),
          flush=True)
    say("servo drive: MPC (FOH) vs PID through the emulated CiA 402 drive (~5 s)")
    servo = run_servo_demo(args.out, echo=None, recording=RecordingOptions(live=first, **live),
                           quiet=args.quiet)
    print("\n" + format_servo_demo(servo), flush=True)
    print(f"\nsessions (.mcap) and reports (.png) in {os.path.abspath(args.out)}; "
          f"'hil report {os.path.join(args.out, 'bench_eec.mcap')}' summarises one (with "
          "'. .venv/bin/activate' first, or as .venv/bin/hil, after make demo)")
    return 0


def progress(message: str) -> None:
    print(f"hil demo: {message} ...", file=sys.stderr, flush=True)


def _bench_session(controller: str, path: str, recording: RecordingOptions, quiet: bool
                   ) -> dict[str, Any]:
    """One 8-cycle run against the emulated bench, plus its report PNG (a worker process)."""
    from hil.bench.run import BenchRunOptions, run_bench
    from hil.core.recording.reader import read_session
    from hil.core.report import plot_session

    kpis = run_bench(BenchRunOptions(controller=controller, cycles=8, out=path,
                                     recording=recording, quiet=quiet)).kpis
    png = os.path.splitext(path)[0] + ".png"
    plot_session(read_session(path), png)
    return {**kpis, "png": png}


def bench_demo(out_dir: str, recording: dict[str, RecordingOptions] | None = None,
               quiet: bool = False) -> str:
    """EEC and BC side by side (two processes: the machine has two cores); ``quiet``: without
    their progress lines."""
    paths = {c: os.path.join(out_dir, f"bench_{c}.mcap") for c in ("eec", "bc")}
    options = recording or {}
    with ProcessPoolExecutor(max_workers=2) as pool:
        futures = {c: pool.submit(_bench_session, c, p, options.get(c, RecordingOptions()),
                                  quiet) for c, p in paths.items()}
        rows = {c: f.result() for c, f in futures.items()}
    return format_bench(rows)


def format_bench(rows: dict[str, dict[str, Any]]) -> str:
    """The comparison table and the peak reduction of the EEC against the BC."""
    header = f"{'bench, 8 cycles':<16}" + "".join(f"{c:>18}" for c in BENCH_COLUMNS)
    lines = [header]
    for name, kpis in rows.items():
        lines.append(f"{name.upper():<16}" + "".join(f"{kpis[c]:>18}" for c in BENCH_COLUMNS))
    eec, bc = rows["eec"], rows["bc"]
    peak = 100.0 * (bc["J2_VA"] - eec["J2_VA"]) / bc["J2_VA"]
    energy = 100.0 * (bc["J1_VA"] - eec["J1_VA"]) / bc["J1_VA"]
    lines.append(f"EEC vs BC: peak J2 {peak:.1f} % lower, energy J1 {energy:.1f} % lower "
                 f"(paper: 11.5 % and 2.8 % with H_s = T)")
    lines.append(f"EEC solve time per decision: median {eec['solve_ms']['median']:.1f} ms, "
                 f"max {eec['solve_ms']['max']:.1f} ms")
    for name, kpis in rows.items():
        lines.append(f"{name.upper()}: {kpis['mcap']}, {kpis['png']}")
    return "\n".join(lines)
