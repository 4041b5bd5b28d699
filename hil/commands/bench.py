"""``hil bench run`` / ``hil bench identify``: the relay bench."""

from __future__ import annotations

import argparse
import json
from typing import Any

from hil.commands.argtypes import nonnegative_float, positive_float, positive_int


def register(subparsers: argparse._SubParsersAction) -> None:
    bench = subparsers.add_parser("bench", help="relay bench: closed-loop runs, identification")
    bench_sub = bench.add_subparsers(dest="bench_command", metavar="COMMAND", required=True)
    run = bench_sub.add_parser(
        "run", help="run EEC or BC against the bench",
        description="Closed-loop run of the energy-efficiency controller (EEC, MILP receding "
        "horizon) or the hysteresis baseline (BC) against the relay bench (the emulator over "
        "Modbus TCP on loopback by default, lockstep unless --realtime). Records an MCAP "
        "session and prints the KPIs. Defaults of the tuning flags come from "
        "hil/configs/eec.toml and bench.toml.",
    )
    run.add_argument("--controller", choices=["eec", "bc"], required=True)
    run.add_argument("--bench", default="emulated",
                     help="emulated | modbus-tcp://HOST:PORT | modbus-rtu:///dev/X")
    run.add_argument("--cycles", type=positive_int, default=8, help="machine cycles (T = 28 s)")
    run.add_argument("--hp", type=positive_int, default=None,
                     help="prediction horizon [s] (default 28)")
    run.add_argument("--hs", type=positive_int, default=None,
                     help="applied part of each plan [s] (default 1: receding horizon)")
    run.add_argument("--gamma1", type=nonnegative_float, default=None,
                     help="weight of energy J1 (default 0.9)")
    run.add_argument("--gamma2", type=nonnegative_float, default=None,
                     help="weight of peak J2 (default 0.1)")
    run.add_argument("--dwell", type=positive_float, default=None,
                     help="min on/off time of P1/P2 [s] (default 5), also in the safety layer")
    run.add_argument("--terminal", choices=["none", "hold"], default=None,
                     help="EEC terminal condition: none (the paper) or hold q_j(H_p) >= q_j(0) "
                          "(default hold)")
    run.add_argument("--disturbance", action="store_true",
                     help="switch the emulator's unknown load on")
    run.add_argument("--realtime", action="store_true",
                     help="follow the wall clock (always so against a real bench)")
    run.add_argument("--config", metavar="F.toml",
                     help="TOML laid over hil/configs/bench.toml and eec.toml")
    run.add_argument("--out", metavar="F.mcap", help="session file (default: a temp file)")
    run.add_argument("--json", action="store_true", help="print KPIs as JSON")
    run.set_defaults(handler=run_command)
    ident = bench_sub.add_parser("identify", help="PRBS switching experiment for identification")
    from hil import bench_identify

    bench_identify.add_arguments(ident)
    ident.set_defaults(handler=bench_identify.command)


def run_command(args: argparse.Namespace) -> int:
    from hil.bench_run import BenchRunOptions, run_bench

    overrides = {"terminal": args.terminal} if args.terminal else {}
    kpis = run_bench(BenchRunOptions(
        controller=args.controller, bench=args.bench, cycles=args.cycles, hp_s=args.hp,
        hs_s=args.hs, gamma1=args.gamma1, gamma2=args.gamma2, dwell_s=args.dwell,
        disturbance=args.disturbance, realtime=args.realtime, out=args.out,
        config_path=args.config, overrides=overrides,
    ))
    print(json.dumps(kpis, indent=2) if args.json else format_kpis(kpis))
    return 0


def format_kpis(kpis: dict[str, Any]) -> str:
    """The KPI dictionary as aligned lines."""
    lines = []
    for key, value in kpis.items():
        if isinstance(value, dict):
            value = ", ".join(f"{k} {v}" for k, v in value.items())
        lines.append(f"{key:<17} {value}")
    return "\n".join(lines)
