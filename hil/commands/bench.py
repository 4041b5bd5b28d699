"""``hil bench run`` / ``hil bench identify``: the relay bench."""

from __future__ import annotations

import argparse

from hil.commands import not_yet_available
from hil.commands.argtypes import positive_float, positive_int


def register(subparsers: argparse._SubParsersAction) -> None:
    bench = subparsers.add_parser("bench", help="relay bench: closed-loop runs, identification")
    bench_sub = bench.add_subparsers(dest="bench_command", metavar="COMMAND", required=True)
    run = bench_sub.add_parser("run", help="run EEC or BC against the bench")
    run.add_argument("--controller", choices=["eec", "bc"], required=True)
    run.add_argument("--bench", default="emulated",
                     help="emulated | modbus-tcp://HOST:PORT | modbus-rtu:///dev/X")
    run.add_argument("--cycles", type=positive_int, default=8, help="machine cycles (T = 28 s)")
    run.add_argument("--hp", type=positive_int, default=28, help="prediction horizon [s]")
    run.add_argument("--hs", type=positive_int, default=1, help="applied part of the plan [s]")
    run.add_argument("--gamma1", type=float, default=0.9, help="weight of energy J1")
    run.add_argument("--gamma2", type=float, default=0.1, help="weight of peak J2")
    run.add_argument("--dwell", type=positive_float, default=5.0, help="min on/off time [s]")
    run.add_argument("--disturbance", action="store_true", help="switch the unknown load on")
    run.add_argument("--realtime", action="store_true", help="follow the wall clock")
    run.add_argument("--out", metavar="F.mcap", help="session file")
    run.add_argument("--json", action="store_true", help="print KPIs as JSON")
    run.set_defaults(handler=not_yet_available("hil bench run"))
    ident = bench_sub.add_parser("identify", help="PRBS switching experiment for identification")
    ident.set_defaults(handler=not_yet_available("hil bench identify"))
