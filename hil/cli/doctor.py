"""``hil doctor``: what this machine grants a real-time loop, and how well it keeps time."""

from __future__ import annotations

import argparse
import sys

from hil.cli.argtypes import positive_float
from hil.cli.output import add_quiet_argument, json_text


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "doctor", help="qualify this machine for real-time runs",
        description="Run the bare fixed-rate loop at 1 kHz and 2 kHz under the hardening a "
        "--realtime session gets (SCHED_FIFO, a pinned core, mlockall, the garbage collector "
        "frozen, 1 ns timer slack) and report its lateness p50/p99/max and skipped ticks, what "
        "the operating system granted, and what an administrator could change.")
    p.add_argument("--duration", type=positive_float, default=5.0, metavar="S",
                   help="seconds per rate (default 5)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    add_quiet_argument(p, "no progress lines on stderr (which rate runs now)")
    p.set_defaults(handler=doctor_command)


def doctor_command(args: argparse.Namespace) -> int:
    from hil.core.doctor import format_doctor, run_doctor

    result = run_doctor(args.duration, progress=None if args.quiet else
                        lambda line: print(line, file=sys.stderr, flush=True))
    print(json_text(result) if args.json else format_doctor(result))
    return 0
