"""``hil twin check``: a recorded run's commands replayed into its twin (the emulator with a
model file, and the drive's EDS), the twin's response set against the recorded one."""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import TYPE_CHECKING

from hil.cli.argtypes import output_file
from hil.cli.output import add_quiet_argument, finite, json_text

if TYPE_CHECKING:  # numpy and the reader load when a check runs, not for --help
    import numpy as np

    from hil.core.recording.reader import SessionData
    from hil.core.twin import Compared, TwinCheck

    #: a check, its time axis [s], and each output's fit with the recorded and twin's series
    Checked = tuple[TwinCheck, np.ndarray, list[Compared]]

#: the fit every output must reach unless --min-fit says [%]
DEFAULT_MIN_FIT_PCT = 80.0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "twin", help="check a twin of your machine against a recording of it",
        description="A twin is hil's emulator loaded with your machine's identified model "
        "(and your drive's EDS). 'hil twin check' tells how close it comes to the machine.")
    commands = p.add_subparsers(dest="twin_command", metavar="COMMAND", required=True)
    check = commands.add_parser(
        "check", help="replay a recording's commands into the twin and compare",
        description="Replay the currents a recorded servo run gave its drive (RECORDED.mcap, "
        "from the machine) into the twin, in lockstep: the drive emulator with --model (and "
        "--eds), the run's cycle period, current limit and reference scenario. Then compare "
        "the twin's response with the recorded one, output by output (position and "
        "velocity): fit [%] (100 (1 - ||y - y_twin|| / ||y - mean y||), as 'hil identify' "
        "reports it), largest and RMS error. Exit status 0 when every output's fit reaches "
        "--min-fit, 1 when one does not, 2 on bad input. A bench session (of 'hil bench "
        "run' or 'hil bench identify') is replayed likewise into the bench emulator: its "
        "relays switched at the ticks they were recorded switching, its config tables "
        "(sampling, relays, sequence, plant and noise seed), each load --model LOAD=F.json "
        "names made that model file; compared on /bench/power's total_va and the loaded "
        "phases' apparent power (va_l1..va_l3).")
    check.add_argument("recorded", metavar="RECORDED.mcap",
                       help="a servo or bench session of the machine")
    check.add_argument("--model", metavar="F.json", action="append", default=[],
                       help="servo: the axis model of the twin, a model file of 'hil identify' "
                       "(default: the emulator's own axis, the servo paper's); bench: "
                       "LOAD=F.json, a load of [plant.loads] made that model file, once per "
                       "load (default: the recorded bench's loads)")
    check.add_argument("--eds", metavar="F.eds",
                       help="servo: the drive's EDS: the twin's dictionary is the drive's")
    check.add_argument("--min-fit", type=fit_percent, default=DEFAULT_MIN_FIT_PCT,
                       metavar="PCT", help="the fit every output must reach [%%] "
                       f"(default {DEFAULT_MIN_FIT_PCT:g})")
    check.add_argument("--out", metavar="F.png", type=output_file,
                       help="also draw recorded and twin, and their error, to this PNG file")
    check.add_argument("--twin-out", metavar="F.mcap", type=output_file,
                       help="the twin's session (default: RECORDED.twin.mcap beside it)")
    check.add_argument("--json", action="store_true",
                       help="print the check as JSON (passed, min_fit_pct, outputs, session)")
    add_quiet_argument(check, "no progress line on the terminal while the twin runs (there "
                       "is none when stderr is not a terminal)")
    check.set_defaults(handler=twin_check_command)


def fit_percent(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a fit in %, at most 100, got {text!r}"
                                         ) from None
    if not value <= 100:
        raise argparse.ArgumentTypeError(f"expected a fit in %, at most 100, got {text}")
    return value


def twin_check_command(args: argparse.Namespace) -> int:
    from hil.bench.twin import is_bench_session
    from hil.core.recording.reader import read_session
    from hil.core.twin import format_check, plot_check
    from hil.errors import UsageError

    data = read_session(args.recorded)
    twin_out = args.twin_out or str(Path(args.recorded).with_suffix(".twin.mcap"))
    if os.path.abspath(twin_out) == os.path.abspath(args.recorded):
        raise UsageError(f"--twin-out {twin_out} is the recording itself; choose another file")
    if is_bench_session(data):
        check, t_s, pairs = bench_check(args, data, twin_out)
    else:
        check, t_s, pairs = servo_check(args, data, twin_out)
    if args.out:
        plot_check(t_s, pairs, args.out,
                   f"twin check: {Path(args.recorded).name} against its twin")
    if args.json:
        print(json_text(finite({**check.document(), "recorded": args.recorded,
                                "session": twin_out, **({"png": args.out} if args.out
                                                        else {})})))
    else:
        print(format_check(check, args.recorded, twin_out))
    return 0 if check.passed else 1


def servo_check(args: argparse.Namespace, data: SessionData, twin_out: str) -> Checked:
    """A servo session's currents replayed into the drive emulator with --model and --eds."""
    from hil.core.recording.reader import read_session
    from hil.errors import UsageError
    from hil.servo.twin import check_twin, read_recording, run_twin

    if len(args.model) > 1:
        raise UsageError(f"--model given {len(args.model)} times: a servo twin takes one "
                         "axis model file")
    model = args.model[0] if args.model else None
    for flag, path in (("--model", model), ("--eds", args.eds)):
        if path is not None and not os.path.isfile(path):
            raise UsageError(f"{flag} {path}: no such file")
    recording = read_recording(data)
    run_twin(recording, model, args.eds, twin_out, args.quiet)
    check, pairs = check_twin(recording, read_session(twin_out), args.min_fit)
    return check, recording.t_s, pairs


def bench_check(args: argparse.Namespace, data: SessionData, twin_out: str) -> Checked:
    """A bench session's relays replayed into the bench emulator with --model LOAD=F.json."""
    from hil.bench.twin import check_twin, parse_models, read_recording, run_twin
    from hil.core.recording.reader import read_session
    from hil.errors import UsageError

    if args.eds is not None:
        raise UsageError(f"--eds {args.eds}: {args.recorded} is a bench session; a bench has "
                         "no drive EDS (its twin takes --model LOAD=F.json)")
    recording = read_recording(data)
    models = parse_models(args.model, recording.loads)
    run_twin(recording, models, twin_out, args.quiet)
    check, pairs = check_twin(recording, read_session(twin_out), args.min_fit)
    return check, recording.t_s, pairs
