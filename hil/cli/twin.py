"""``hil twin check``: a recorded run's commands replayed into its twin (the emulator with a
model file, and the drive's EDS), the twin's response set against the recorded one."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from hil.cli.argtypes import output_file
from hil.cli.output import finite, json_text

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
        "--min-fit, 1 when one does not, 2 on bad input.")
    check.add_argument("recorded", metavar="RECORDED.mcap", help="a servo session of the machine")
    check.add_argument("--model", metavar="F.json",
                       help="the axis model of the twin, a model file of 'hil identify' "
                       "(default: the emulator's own axis, the servo paper's)")
    check.add_argument("--eds", metavar="F.eds",
                       help="the drive's EDS: the twin's dictionary is the drive's")
    check.add_argument("--min-fit", type=fit_percent, default=DEFAULT_MIN_FIT_PCT,
                       metavar="PCT", help="the fit every output must reach [%%] "
                       f"(default {DEFAULT_MIN_FIT_PCT:g})")
    check.add_argument("--out", metavar="F.png", type=output_file,
                       help="also draw recorded and twin, and their error, to this PNG file")
    check.add_argument("--twin-out", metavar="F.mcap", type=output_file,
                       help="the twin's session (default: RECORDED.twin.mcap beside it)")
    check.add_argument("--json", action="store_true",
                       help="print the check as JSON (passed, min_fit_pct, outputs, session)")
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
    from hil.core.recording.reader import read_session
    from hil.core.twin import format_check, plot_check
    from hil.errors import UsageError
    from hil.servo.twin import check_twin, read_recording, run_twin

    for flag, path in (("--model", args.model), ("--eds", args.eds)):
        if path is not None and not os.path.isfile(path):
            raise UsageError(f"{flag} {path}: no such file")
    recording = read_recording(read_session(args.recorded))
    twin_out = args.twin_out or str(Path(args.recorded).with_suffix(".twin.mcap"))
    if os.path.abspath(twin_out) == os.path.abspath(args.recorded):
        raise UsageError(f"--twin-out {twin_out} is the recording itself; choose another file")
    run_twin(recording, args.model, args.eds, twin_out)
    check, pairs = check_twin(recording, read_session(twin_out), args.min_fit)
    if args.out:
        plot_check(recording.t_s, pairs, args.out,
                   f"twin check: {Path(args.recorded).name} against its twin")
    if args.json:
        print(json_text(finite({**check.document(), "recorded": args.recorded,
                                "session": twin_out, **({"png": args.out} if args.out
                                                        else {})})))
    else:
        print(format_check(check, args.recorded, twin_out))
    return 0 if check.passed else 1
