"""The report's tables, for one session or side by side for several (a column each): the
damage of a recovered file, metadata, KPIs with their limits and verdicts, events, loop timing,
the kind's own section, and a comparison's rows."""

from __future__ import annotations

import html
import json
import shlex
from collections.abc import Mapping, Sequence
from typing import Any

from hil.core.html_report.page import paragraph, section, table
from hil.core.loop import PHASES
from hil.core.recording.reader import SessionData
from hil.core.report import find_summary
from hil.core.verdict import unit_of

MAX_EVENTS = 500


def damage(summaries: Sequence[Mapping[str, Any]], labels: Sequence[str]) -> str:
    """What could not be read (a truncated or damaged file), how the recording ended and what
    the recorder dropped; nothing for intact sessions."""
    parts = []
    for summary, label in zip(summaries, labels, strict=True):
        lines = _damage_lines(summary)
        if lines:
            head = f"<h3>{html.escape(label)}: {html.escape(summary['file'])}</h3>" \
                if len(labels) > 1 else ""
            items = "".join(f"<li>{html.escape(line)}</li>" for line in lines)
            parts.append(f'<div class="damage">{head}<ul>{items}</ul></div>')
    return section("Damage: a recovered file", *parts, anchor="damage") if parts else ""


def _damage_lines(summary: Mapping[str, Any]) -> list[str]:
    lines = []
    if summary["recovered"] or summary["damage"]:
        lost = summary["lost_messages"]
        lines.append(f"RECOVERED: {summary['lost_bytes']} byte(s) unreadable, "
                     f"{'an unknown number of' if lost is None else lost} message(s) lost; "
                     "everything readable is shown")
    for d in summary["damage"]:
        where = f"from byte {d['offset']}"
        if "start_ns" in d:
            where += f", log time {d['start_ns'] / 1e9:.3f}..{d['end_ns'] / 1e9:.3f} s"
        count = f"{d['messages']} message(s)" if "messages" in d else "messages unknown"
        lines.append(f"{d['kind']}: {d['bytes']} byte(s) {where}: {count}"
                     + (f" ({d['reason']})" if d.get("reason") else ""))
    if summary["ended"]:
        lines.append(f"ended abnormally: {summary['ended']}")
    if summary["dropped"]:
        lines.append("dropped by the recorder: " + ", ".join(
            f"{topic} {count}" for topic, count in summary["dropped"].items()))
    return lines


def metadata(sessions: Sequence[SessionData], summaries: Sequence[Mapping[str, Any]],
             labels: Sequence[str]) -> str:
    """The session(s): file, kind, clock, start, duration, command, versions; topics."""
    def meta(data: SessionData, table_name: str, key: str) -> Any:
        return data.metadata.get(table_name, {}).get(key)

    def command(data: SessionData) -> str | None:
        argv = meta(data, "session", "argv")
        try:
            return shlex.join(json.loads(argv)) if argv else None
        except (ValueError, TypeError):
            return argv

    fields: list[tuple[str, Any]] = [
        ("file", lambda d, s: s["file"]),
        ("files", lambda d, s: len(s["files"])),
        ("kind", lambda d, s: s["kind"] or None),
        ("clock", lambda d, s: s["clock"] or None),
        ("started", lambda d, s: meta(d, "session", "start_wall_time")),
        ("duration [s]", lambda d, s: s["duration_s"]),
        ("command", lambda d, s: command(d)),
        ("controller", lambda d, s: s["kpis"].get("controller")),
        ("status", lambda d, s: s["kpis"].get("status")),
        ("stop reason", lambda d, s: s["kpis"].get("stop_reason")),
        ("hil", lambda d, s: meta(d, "versions", "hil")),
        ("python", lambda d, s: meta(d, "versions", "python")),
        ("events (info / warning / error)",
         lambda d, s: " / ".join(str(s["events"][k]) for k in ("info", "warning", "error"))),
    ]
    rows = [[name, *(get(d, s) for d, s in zip(sessions, summaries, strict=True))]
            for name, get in fields]
    topics = sorted({t for s in summaries for t in s["topics"]})
    topic_rows = [[t, *(s["topics"].get(t, 0) for s in summaries)] for t in topics]
    columns = list(labels) if len(labels) > 1 else ["value"]
    return section("Session", table(["", *columns], rows),
                   "<h3>Topics (messages)</h3>",
                   table(["topic", *columns], topic_rows), anchor="session")


def _flat(kpis: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested KPIs as ``group.key`` rows (the ``limits`` rows left out: they have a table)."""
    rows: dict[str, Any] = {}
    for key, value in kpis.items():
        if isinstance(value, Mapping):
            rows.update(_flat(value, f"{prefix}{key}."))
        elif not (key == "limits" and not prefix):
            rows[f"{prefix}{key}"] = value if not isinstance(value, list) else json.dumps(value)
    return rows


def kpis(summaries: Sequence[Mapping[str, Any]], labels: Sequence[str]) -> str:
    """The KPIs (a column per session, with their units) and the limits with their
    verdicts."""
    flat = [_flat(s["kpis"]) for s in summaries]
    names = list(dict.fromkeys(name for f in flat for name in f))
    if not names:
        return section("KPIs", paragraph("The session recorded no KPIs."), anchor="kpis")
    columns = list(labels) if len(labels) > 1 else ["value"]
    rows = [[name, unit_of(name), *(f.get(name) for f in flat)] for name in names]
    return section("KPIs", table(["KPI", "unit", *columns], rows), _limits(summaries, labels),
                   anchor="kpis")


def _limits(summaries: Sequence[Mapping[str, Any]], labels: Sequence[str]) -> str:
    by_limit: dict[str, list[Mapping[str, Any] | None]] = {}
    for index, summary in enumerate(summaries):
        for result in summary["kpis"].get("limits", []) or []:
            if isinstance(result, Mapping):
                row = by_limit.setdefault(str(result.get("limit")), [None] * len(summaries))
                row[index] = result
    if not by_limit:
        return paragraph("No limits were set on this run: no verdict.")
    rows, classes = [], []
    for limit, results in by_limit.items():
        cells: list[Any] = [limit]
        for result in results:
            if result is None:
                cells += [None, ("not checked", "verdict")]
            else:
                cells += [result.get("measured"),
                          ("holds" if result.get("passed") else "VIOLATED", "verdict")]
        rows.append(cells)
        failed = any(r is not None and not r.get("passed") for r in results)
        classes.append("fail" if failed else "pass")
    headers = ["limit"]
    for label in (labels if len(labels) > 1 else [""]):
        headers += [f"measured {label}".strip(), f"verdict {label}".strip()]
    return "<h3>Limits</h3>" + table(headers, rows, classes)


def events(sessions: Sequence[SessionData], labels: Sequence[str]) -> str:
    """Every event (the first ``MAX_EVENTS`` of a session that has more, saying so)."""
    parts = []
    for data, label in zip(sessions, labels, strict=True):
        span = data.time_range_ns()
        start = span[0] if span else 0
        found = data.topic("/events")
        rows = [[(t - start) / 1e9, e.get("level", ""), e.get("source", ""),
                 e.get("kind", ""), e.get("message", "")]
                for t, e in found[:MAX_EVENTS] if isinstance(e, dict)]
        if len(labels) > 1:
            parts.append(f"<h3>{html.escape(label)}</h3>")
        if len(found) > MAX_EVENTS:
            parts.append(paragraph(f"The first {MAX_EVENTS} of {len(found)} events; "
                                   "`hil report --events` lists them all.", "note"))
        parts.append(table(["time [s]", "level", "source", "kind", "message"], rows)
                     if rows else paragraph("No events."))
    return section("Events", *parts, anchor="events")


def loop(summaries: Sequence[Mapping[str, Any]], labels: Sequence[str], histogram: str
         ) -> str:
    """Per task: runs, missed, overruns, lateness and tick time (its run in a tick, every
    phase: p50 / p99 / max, us), the phases' p50 / p99; then the tick-time histogram."""
    rows = []
    for summary, label in zip(summaries, labels, strict=True):
        for task, s in summary["loop"].items():
            lat, tick = s["lateness_us"], s["tick_us"]
            phases = ", ".join(f"{p} {s[f'{p}_us']['p50']:.1f}/{s[f'{p}_us']['p99']:.1f}"
                               for p in PHASES if f"{p}_us" in s)
            rows.append([*([label] if len(labels) > 1 else []), task, s["period_s"],
                         s["runs"], s["missed"], s["overruns"],
                         f"{lat['p50']:.1f} / {lat['p99']:.1f} / {lat['max']:.1f}",
                         f"{tick['p50']:.1f} / {tick['p99']:.1f} / {tick['max']:.1f}", phases])
    if not rows:
        return section("Loop timing", paragraph("No loop timing was recorded."),
                       anchor="loop")
    headers = [*(["session"] if len(labels) > 1 else []), "task", "period [s]", "runs",
               "missed", "overruns", "lateness p50 / p99 / max [us]",
               "tick p50 / p99 / max [us]", "phases p50/p99 [us]"]
    return section("Loop timing", table(headers, rows), histogram, anchor="loop")


def kind_sections(summaries: Sequence[Mapping[str, Any]], labels: Sequence[str]) -> str:
    """The session kind's own part of ``hil report`` (servo: feedback timing; bench: the
    EEC's solve times), as its text."""
    parts = []
    for summary, label in zip(summaries, labels, strict=True):
        extra = find_summary(summary["kind"])
        if extra is not None and extra.key in summary:
            head = f"{label}\n" if len(labels) > 1 else ""
            parts.append(f"<pre>{html.escape(head + chr(10).join(extra.lines(summary[extra.key])))}"
                         "</pre>")
    return section(f"{summaries[0]['kind']} details", *parts, anchor="details") \
        if parts else ""


def comparison_rows(comparison: Mapping[str, Any]) -> str:
    """A comparison's table: KPI or signal, baseline, candidate, difference, tolerance, where
    the worst difference was, and pass / fail; failures first in colour."""
    rows, classes = [], []
    for row in comparison.get("rows", []):
        rows.append([row.get("kind"), row.get("name"), row.get("baseline"),
                     row.get("candidate"), row.get("difference"), row.get("tolerance"),
                     row.get("worst_t_s"),
                     ("pass" if row.get("passed") else "FAIL", "verdict")])
        classes.append("pass" if row.get("passed") else "fail")
    notes = "".join(paragraph(str(note), "note") for note in comparison.get("notes", []))
    return section("Comparison",
                   table(["kind", "name", "baseline", "candidate", "difference", "tolerance",
                          "worst at [s]", "verdict"], rows, classes), notes,
                   anchor="comparison")
