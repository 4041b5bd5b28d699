"""``hil bench run`` / ``hil bench identify``: the relay bench."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from hil.bench.identify_options import MACHINING_MODES, IdentifyOptions, parse_relays
from hil.cli.argtypes import key_value, nonnegative_float, output_file, positive_float, positive_int
from hil.cli.output import add_quiet_argument, json_text
from hil.cli.place import add_place_arguments, run_on_place
from hil.cli.recording import add_recording_arguments
from hil.cli.units import seconds
from hil.cli.verdict import add_controller_arguments, add_junit_argument
from hil.core.recording.writer_fork import start_server

if TYPE_CHECKING:
    from hil.bench.run import BenchRunOptions
    from hil.cli.application import RunApplication


def register(subparsers: argparse._SubParsersAction) -> None:
    bench = subparsers.add_parser("bench", help="relay bench: closed-loop runs, identification")
    bench_sub = bench.add_subparsers(dest="bench_command", metavar="COMMAND", required=True)
    run = bench_sub.add_parser(
        "run", help="run a controller (EEC, BC or your own) against the bench",
        description="Closed-loop run of a bench controller against the relay bench (the "
        "emulator over Modbus TCP on loopback by default, lockstep unless --realtime): the "
        "energy-efficiency controller (eec, MILP receding horizon), the hysteresis baseline "
        "(bc), or your own class with decide(obs) -> {relay: bool}, built as Class(params). "
        "Relays always go through the safety layer (dwell, safe levels). Records an MCAP "
        "session and prints the KPIs; with --limit, the verdict is the exit status (0 all "
        "hold, 1 one is violated, 2 usage or configuration error, 3 completed with faults: "
        "the bench misbehaved, see docs/FAULTS.md). Defaults of the tuning "
        "flags come from hil/configs/eec.toml and bench.toml.",
    )
    add_run_arguments(run)
    add_junit_argument(run)
    run.add_argument("--out", metavar="F.mcap", type=output_file, help="session file (default: "
                     "sessions/bench-CONTROLLER-DATE-TIME.mcap)")
    run.add_argument("--json", action="store_true", help="print KPIs as JSON")
    run.add_argument("--print-config", action="store_true",
                     help="print every setting as the run would use it, with where it came "
                     "from (built-in default, hil/configs/bench.toml or eec.toml, --config, a "
                     "flag), and exit without running; with --json as JSON")
    add_recording_arguments(run)
    add_place_arguments(run, "bench")
    run.set_defaults(handler=run_command)
    ident = bench_sub.add_parser("identify", help="PRBS switching experiment for identification")
    add_identify_arguments(ident)
    ident.set_defaults(handler=identify_command)


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of ``hil bench run`` that make up the experiment (shared with ``hil sweep
    bench``): the controller, its tuning, the bench and the verdict."""
    add_controller_arguments(parser, "eec, bc", "total_va or any meter quantity polled, and the "
                             "levels q1, q2")
    parser.add_argument("--bench", metavar="URL",
                        help="where the bench is (default: bench.toml's [bus] url, emulated): "
                        "emulated | modbus-tcp://HOST:PORT | modbus-rtu:///dev/X")
    length = parser.add_mutually_exclusive_group()
    length.add_argument("--cycles", type=positive_int,
                        help="machine cycles (T = 28 s each; default 8)")
    length.add_argument("--duration", type=seconds, metavar="S",
                        help="the run's length [s of session time] instead of whole cycles "
                        "(a real-time smoke test: --duration 2 --realtime); the KPI cycles is "
                        "then the share of cycles it lasted")
    parser.add_argument("--hp", type=positive_int, metavar="S",
                        help="prediction horizon [s] (eec.hp_s, default 28)")
    parser.add_argument("--hs", type=positive_int, metavar="S",
                        help="applied part of each plan [s] (eec.hs_s, default 1: receding "
                        "horizon)")
    parser.add_argument("--gamma1", type=nonnegative_float,
                        help="weight of energy J1 (eec.gamma1, default 0.9)")
    parser.add_argument("--gamma2", type=nonnegative_float,
                        help="weight of peak J2 (eec.gamma2, default 0.1)")
    parser.add_argument("--dwell", type=seconds, metavar="S",
                        help="min on/off time of P1/P2 [s] (relays.P*.dwell_s, default 5), also "
                        "in the safety layer: may lengthen it, shorten it only with "
                        "--allow-looser-safety")
    parser.add_argument("--terminal", choices=["none", "hold"],
                        help="EEC terminal condition: none (the paper) or hold q_j(H_p) >= q_j(0) "
                        "(eec.terminal, default hold)")
    parser.add_argument("--disturbance", action="store_true",
                        help="switch the emulator's unknown load on (plant.disturbance.enabled)")
    parser.add_argument("--realtime", action="store_true",
                        help="follow the wall clock (always so against a real bench)")
    parser.add_argument("--config", metavar="F.toml",
                        help="TOML laid over hil/configs/bench.toml and eec.toml")
    add_quiet_argument(parser)
    parser.add_argument("--safety", action="append", type=key_value, default=[],
                        metavar="KEY=VALUE",
                        help="tighten one safety limit of bench.toml's [safety] for this run "
                        "(repeat): max_total_va, max_total_va_ms, level_min, level_max, "
                        "enabled; a looser value needs --allow-looser-safety")
    parser.add_argument("--allow-looser-safety", action="store_true",
                        help="let --safety and --dwell loosen a limit of the config (recorded "
                        "as a warning in the session)")


def application() -> RunApplication[BenchRunOptions]:
    """``hil bench run``'s application (its modules load here)."""
    from hil.bench.run import BenchRunOptions, run_bench
    from hil.bench.settings import resolve_bench
    from hil.cli.application import RunApplication

    return RunApplication("hil bench run", BenchRunOptions.from_flags,
                          lambda options: resolve_bench(options).settings(), run_bench,
                          lambda _options, kpis: format_kpis(kpis))


def run_command(args: argparse.Namespace) -> int:
    start_server()  # beside this command's imports: its first session finds it up
    return run_on_place(args, "bench", lambda: application().command_line(args))


def format_kpis(kpis: dict[str, Any]) -> str:
    """The KPIs as aligned lines, as a person reads them (:mod:`hil.core.kpi_text`); the two
    wall-clock figures say what each timed (the loop's pace is not the whole run's)."""
    from hil.core.kpi_text import kpi_rows

    pace = {"wall_s": " s (the run, its start and safe stop included)",
            "realtime_factor": "x real time (session time over the time the loop ticked)"}
    return "\n".join(f"{name:<17} {text}{pace[name] if name in pace and text != '-' else ''}"
                     for name, text in kpi_rows(kpis))


def add_identify_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of ``hil bench identify`` (an argparse parser)."""
    parser.description = (
        "Identification experiment: switch the chosen relays with seeded pseudo-random binary "
        "sequences (every hold at least the relay's dwell, so the safety layer never defers a "
        "switch) against the bench (the emulator over Modbus TCP on loopback by default, "
        "lockstep unless --realtime), record the session (kind bench-identify: meter, levels, "
        "relays and the written PRBS on /ident/relays) and print the 'hil identify' command "
        "lines for the loads it excited.")
    parser.add_argument("--relays", type=parse_relays, default=("P1", "P2"),
                        help="relays switched by PRBS, comma-separated, or none (default P1,P2)")
    parser.add_argument("--duration", type=positive_float, default=300.0, metavar="S",
                        help="length of the experiment [s] (default 300)")
    parser.add_argument("--min-hold", type=positive_float, default=None, metavar="S",
                        help="bit length of the PRBS = shortest hold [s] (default: each relay's "
                        "dwell; shorter than the dwell is refused)")
    parser.add_argument("--seed", type=int, default=1, help="PRBS seed (default 1)")
    parser.add_argument("--bench", metavar="URL",
                        help="emulated (default) | modbus-tcp://HOST:PORT | "
                        "modbus-rtu:///dev/X")
    parser.add_argument("--machining", choices=MACHINING_MODES, default="off",
                        help="M1/M2: play the machining sequence, switch them by PRBS too, or "
                        "leave them off (default off)")
    parser.add_argument("--output-quantity", default="va_l2", metavar="QUANTITY",
                        help="meter quantity the printed commands identify (default va_l2; "
                        "e.g. total_va)")
    parser.add_argument("--progress", type=nonnegative_float, default=10.0, metavar="S",
                        help="progress line on stderr every S seconds of experiment time "
                        "(0 = none; default 10)")
    add_quiet_argument(parser, "no progress lines (as --progress 0)")
    parser.add_argument("--realtime", action="store_true",
                        help="follow the wall clock (always so against a real bench)")
    parser.add_argument("--config", metavar="F.toml", help="TOML laid over hil/configs/bench.toml")
    parser.add_argument("--out", metavar="F.mcap", type=output_file,
                        help="session file (default: sessions/bench-identify-DATE-TIME.mcap)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    add_place_arguments(parser, "bench")


def identify_command(args: argparse.Namespace) -> int:
    """Handler of ``hil bench identify``."""
    start_server()  # beside this command's imports: its first session finds it up
    return run_on_place(args, "bench", lambda: _identify(args))


def _identify(args: argparse.Namespace) -> int:
    from hil.bench.identify import run_identify_experiment

    summary = run_identify_experiment(IdentifyOptions(
        relays=args.relays, duration_s=args.duration, min_hold_s=args.min_hold, seed=args.seed,
        bench=args.bench or "emulated", machining=args.machining,
        meter_quantity=args.output_quantity, realtime=args.realtime, out=args.out,
        config_path=args.config, progress_s=0.0 if args.quiet else args.progress,
        lab=getattr(args, "lab", None),
    ))
    if args.json:
        print(json_text(summary))
        return 0
    print(f"session:   {summary['mcap']}")
    switches = ", ".join(f"{n} {c}" for n, c in summary["switches"].items()) or "none"
    if summary["sequence_relays"]:
        switches += f"; the machining sequence plays {', '.join(summary['sequence_relays'])}"
    print(f"switches:  {switches}")
    print(f"deferred:  {summary['deferred_requests']} (safety layer), failed writes "
          f"{summary['failed_writes']}, missed meter polls {summary['missed_power']}")
    print("identify with:")
    for entry in summary["identify_commands"]:
        print(f"  # {entry['target']}")
        print(f"  {entry['command']}")
    return 0
