"""``hil report``: KPIs, loop timing and plots of any session file, truncated ones included."""

from __future__ import annotations

import argparse

from hil.cli.output import json_text
from hil.core.reader import read_session
from hil.core.report import format_summary, plot_session, summarize


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "report",
        help="summarise a session file (topics, duration, loop timing, KPIs) and plot it",
        description="Summarise a recorded session: topics and message counts, duration, loop "
        "timing per task, events and KPIs. Works on truncated files (e.g. after a crash): "
        "every complete chunk is recovered and the summary says how much was lost.",
    )
    p.add_argument("file", help="session file (.mcap)")
    p.add_argument("--out", metavar="F.png", help="also draw the session to this PNG file")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    data = read_session(args.file)
    summary = summarize(data)
    if args.out:
        plot_session(data, args.out)
        summary["png"] = args.out
    print(json_text(summary) if args.json else format_summary(summary))
    return 0
