"""``hil compare``: a candidate session held against a baseline, KPI by KPI and signal by
signal, each within its tolerance; the exit status is the verdict."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from hil.cli.argtypes import output_file
from hil.cli.output import json_text
from hil.cli.report import points_per_trace
from hil.errors import UsageError

if TYPE_CHECKING:
    from hil.compare.tolerances import Tolerance


def _entry(text: str) -> tuple[str, Tolerance]:
    """``--tolerance NAME=SPEC`` as an argparse type (a bad one: argparse's one line)."""
    from hil.compare.tolerances import parse_entry  # not at import: hil.compare needs numpy

    try:
        return parse_entry(text)
    except UsageError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--tolerance ")) from None


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "compare", help="hold a session against a baseline session: KPIs and signals "
        "within tolerances",
        description="Compare CANDIDATE with BASELINE: every KPI both recorded (nested keys "
        "joined by '.'; the ones that time the computer - wall_s, realtime_factor, step_us, "
        "solve_ms, deadline_misses - only when a tolerance names them) and every --signal, "
        "on session time: lockstep sessions tick for tick, real-time ones by interpolating "
        "the candidate onto the baseline's ticks. A tolerance is exact, abs:V, rel:P% or "
        "tube:V,LAG (a band of V the candidate may lead or lag by LAG, e.g. tube:0.01,2ms), "
        "or one-sided, to ask 'did it get worse?': max:V (at most V above the baseline, any "
        "amount below), min:V (at most V below), worse:V (V the worse way of a KPI whose "
        "better direction is known: errors, misses, violations, faults and the bench's costs "
        "lower, realtime_factor higher; under '*' a KPI or signal better neither way is held "
        "both ways), each V also as P% of the baseline (worse:P%). Without one: exact when "
        "both sessions are lockstep; in real time rel:5% for a KPI, "
        "and a signal needs one. Split series and damaged files are read as 'hil report' "
        "reads them. Prints a table (baseline, candidate, difference, tolerance, the time "
        "of a signal's worst tick, verdict) and one summary line. Exit status: 0 within "
        "tolerance, 1 outside (the summary names each KPI or signal and the time of its "
        "largest excursion), 2 the sessions cannot be compared (applications, rates, a "
        "signal missing in one).",
    )
    p.add_argument("baseline", help="the baseline session (.mcap, split series or folder)")
    p.add_argument("candidate", help="the session to check against it")
    p.add_argument("--signal", action="append", default=[], metavar="TOPIC:FIELD",
                   help="a signal to compare (repeat), e.g. /drive/feedback:position_deg")
    p.add_argument("--tolerance", action="append", default=[], type=_entry,
                   metavar="NAME=SPEC", help="the tolerance of a KPI or signal (repeat; a "
                   "signal named here is compared): exact, abs:V, rel:P%%, tube:V,LAG, "
                   "max:V, min:V, worse:V (V or P%%); "
                   "NAME '*' for everything else (a tube: every signal); laid over --tolerances")
    p.add_argument("--tolerances", metavar="F.toml",
                   help="tolerances from a TOML file: NAME = \"SPEC\" lines, e.g. "
                   "rms_error_deg = \"rel:2%%\", \"/drive/feedback:position_deg\" = "
                   "\"tube:0.01,2ms\", \"*\" = \"abs:0.001\"")
    p.add_argument("--json", action="store_true", help="print the comparison as JSON")
    p.add_argument("--html", metavar="F.html", type=output_file,
                   help="also write the comparison as one self-contained HTML page: its table, "
                   "both sessions' signals overlaid (the compared ones with their worst point "
                   "marked), KPIs, events, loop timing")
    p.add_argument("--max-points", type=points_per_trace, default=None, metavar="N",
                   help="with --html: at most N points per plotted trace (default 5000; "
                   "longer signals are decimated, keeping every peak)")
    p.set_defaults(handler=compare_command)


def compare_command(args: argparse.Namespace) -> int:
    from hil.compare import compare_data, tolerances_file
    from hil.compare.table import format_table, summary_line
    from hil.core.recording.reader import read_session

    tolerances = tolerances_file(args.tolerances) if args.tolerances else {}
    tolerances.update(dict(args.tolerance))
    if args.max_points is not None and not args.html:
        raise UsageError("--max-points N (points per trace) needs --html F.html")
    baseline, candidate = read_session(args.baseline), read_session(args.candidate)
    comparison = compare_data(baseline, candidate, args.signal, tolerances)
    document = comparison.to_json()
    if args.html:  # from the sessions as read for the comparison, not read again
        from hil.core.html_report import DEFAULT_MAX_POINTS, write_comparison_data_html

        write_comparison_data_html(baseline, candidate, document, args.html,
                                   signals=args.signal,
                                   max_points=args.max_points or DEFAULT_MAX_POINTS)
        document["html"] = args.html
    print(json_text(document) if args.json else format_table(comparison))
    print(f"hil: {summary_line(comparison)}", file=sys.stderr)
    return 0 if comparison.passed else 1
