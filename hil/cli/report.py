"""``hil report``: KPIs, loop timing and plots of any session file, truncated ones included;
its events and any topic's messages as text; a self-contained HTML page of it (``--html``)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from hil.cli.argtypes import output_file, positive_int
from hil.cli.output import finite, json_text
from hil.errors import UsageError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "report",
        help="summarise a session file (topics, duration, loop timing, KPIs), list its "
        "events or messages, plot it",
        description="Summarise a recorded session: topics and message counts, duration, loop "
        "timing per task, events and KPIs. Works on truncated files (e.g. after a crash) and "
        "split series (give the first file): every complete chunk is recovered and the "
        "summary says how much was lost. --events lists every event, --topic prints a topic's "
        "messages as JSON lines (see also 'hil export'). --html writes the whole report as "
        "one HTML page that opens offline, with interactive plots.",
    )
    p.add_argument("file", help="session file (.mcap; the first file of a split series)")
    p.add_argument("--out", metavar="F.png", type=output_file,
                   help="also draw the session to this PNG file")
    p.add_argument("--html", metavar="F.html", type=output_file,
                   help="also write a self-contained HTML report (opens offline in any "
                   "browser): metadata, KPIs and limits, events, loop timing, damage, "
                   "interactive plots")
    p.add_argument("--max-points", metavar="N", type=points_per_trace, default=None,
                   help="with --html: draw each signal with at most N points (min/max "
                   "decimation, said on the page; default 5000)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--events", action="store_true",
                   help="list every event: time [s] from the session's start, level, kind, "
                   "message")
    p.add_argument("--topic", metavar="TOPIC",
                   help="print every message of TOPIC as one JSON line "
                   "({\"t_s\": ..., \"log_time_ns\": ..., fields...})")
    p.set_defaults(handler=report_command)


def report_command(args: argparse.Namespace) -> int:
    from hil.core.recording.reader import read_session
    from hil.core.report import format_summary, plot_session, summarize

    if args.max_points is not None and not args.html:
        raise UsageError("--max-points N (points per trace) needs --html F.html")
    if args.html and (args.events or args.topic):
        raise UsageError("--html reports the whole session: not with --events or --topic")
    data = read_session(args.file)
    if args.events or args.topic:
        for line in (event_lines(data) if args.events else topic_lines(data, args.topic)):
            print(line)
        return 0
    summary = summarize(data)
    if args.out:
        plot_session(data, args.out)
        summary["png"] = args.out
    if args.html:
        summary["html"] = write_html(data, args.html, args.max_points).path
    print(json_text(summary) if args.json else format_summary(summary))
    return 0


def points_per_trace(text: str) -> int:
    """``--max-points``: an integer of at least 2 (a trace's smallest and largest sample)."""
    value = positive_int(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f"expected at least 2 points per trace, got {value}")
    return value


def write_html(data: Any, out: str, max_points: int | None) -> Any:
    """``--html``: the session's HTML report (its :class:`~hil.core.html_report.HtmlStats`)."""
    from hil.core.html_report import DEFAULT_MAX_POINTS, write_session_data_html

    return write_session_data_html(data, out, max_points=max_points or DEFAULT_MAX_POINTS)


def start_ns(data: Any) -> int:
    """The session's first log time [ns], which its ``t_s`` count from (0 when empty)."""
    span = data.time_range_ns()
    return span[0] if span else 0


def event_lines(data: Any) -> list[str]:
    """``/events`` as aligned lines: seconds from the start, level, kind, message."""
    start = start_ns(data)
    return [f"{(t - start) / 1e9:10.4f}  {event.get('level', ''):<7}  "
            f"{event.get('kind', ''):<24}  {event.get('message', '')}"
            for t, event in data.topic("/events")]


def topic_lines(data: Any, topic: str) -> list[str]:
    """Every message of ``topic`` as a JSON line; an unknown topic names the ones there are."""
    if topic not in data.messages:
        raise UsageError(f"no topic {topic!r} in {data.path}; topics: "
                         f"{', '.join(sorted(data.messages))}")
    start = start_ns(data)
    lines = []
    for t, message in data.topic(topic):
        fields = message if isinstance(message, dict) else {"value": message}
        row = {"t_s": round((t - start) / 1e9, 9), "log_time_ns": t, **fields}
        lines.append(json.dumps(finite(row), default=_plain))
    return lines


def _plain(value: Any) -> Any:
    return value.tolist() if hasattr(value, "tolist") else str(value)
