"""A self-contained HTML report of a session, or of a comparison of two: one file with
plotly.js inlined that opens offline in any browser (no server, nothing loaded from outside).

It holds the damage of a recovered file, the interactive plots of the session kind's signals
(a comparison: baseline dotted, candidate solid, the compared signals with their worst point),
the KPIs with their limits and verdicts, the events, the loop timing and the metadata. Every
trace is drawn with at most ``max_points`` points (min/max decimation: every peak is kept);
the page says which traces were decimated.

    from hil.core.html_report import write_session_html
    stats = write_session_html("run.mcap", "run.html")
"""

from __future__ import annotations

import html
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

from hil.core.html_report import figures, sections
from hil.core.html_report.page import badge, document, paragraph, section, text
from hil.core.html_report.panels import Panel, Trace, session_panels, signal_trace
from hil.core.recording.reader import SessionData, read_session
from hil.core.report import summarize
from hil.core.verdict import unit_of
from hil.errors import UsageError

__all__ = ["DEFAULT_MAX_POINTS", "HtmlStats", "Panel", "Trace", "write_comparison_data_html",
           "write_comparison_html", "write_session_data_html", "write_session_html"]

DEFAULT_MAX_POINTS = 5000
PLOT_CONFIG = {"displaylogo": False, "responsive": True}


@dataclass(frozen=True)
class HtmlStats:
    """What was written: the file, its size [bytes], its plotly figures, the signals drawn
    over time (``traces``) with their ``points``, and those drawn decimated (``panel:
    trace``) to at most ``max_points`` each."""

    path: str
    bytes: int
    plots: int
    traces: int
    points: int
    decimated: tuple[str, ...]
    max_points: int


def write_session_html(session_path: str, out_path: str, *,
                       max_points: int = DEFAULT_MAX_POINTS) -> HtmlStats:
    """The report of the session at ``session_path`` (a file, a split series, a truncated
    file) written to ``out_path``."""
    _check_points(max_points)
    return write_session_data_html(read_session(session_path), out_path,
                                   max_points=max_points)


def write_session_data_html(data: SessionData, out_path: str, *,
                            max_points: int = DEFAULT_MAX_POINTS) -> HtmlStats:
    """:func:`write_session_html` of a session already read."""
    _check_points(max_points)
    summary = summarize(data)
    drawn = figures.Drawn(max_points)
    rows = figures.overlay([session_panels(data)])
    title = f"hil report: {os.path.basename(data.path)}"
    head = [f"<h1>{html.escape(title)}</h1>",
            f"<p>{_session_badge(summary['kpis'])} {html.escape(_headline(summary))}</p>",
            *(paragraph(f"UNSAFE: {line}", "damage") for line in summary["unsafe"])]
    return _write(out_path, title, head, [data], [summary], ["session"], rows, "", drawn)


def write_comparison_html(baseline_path: str, candidate_path: str,
                          comparison: Mapping[str, Any], out_path: str, *,
                          signals: Sequence[str] = (),
                          max_points: int = DEFAULT_MAX_POINTS) -> HtmlStats:
    """The report of ``comparison`` (the document of ``hil compare --json``) of the two
    sessions, written to ``out_path``: its table, both sessions' panels overlaid, and each
    of ``signals`` and of the comparison's signal rows (``/topic:field``) overlaid with the
    point of its largest difference marked; on the comparison's session time (its
    ``origins_ns``) where it gives one."""
    _check_points(max_points)
    return write_comparison_data_html(read_session(baseline_path), read_session(candidate_path),
                                      comparison, out_path, signals=signals,
                                      max_points=max_points)


def write_comparison_data_html(baseline: SessionData, candidate: SessionData,
                               comparison: Mapping[str, Any], out_path: str, *,
                               signals: Sequence[str] = (),
                               max_points: int = DEFAULT_MAX_POINTS) -> HtmlStats:
    """:func:`write_comparison_html` of two sessions already read."""
    _check_points(max_points)
    labels = ["baseline", "candidate"]
    sessions = [baseline, candidate]
    summaries = [summarize(data) for data in sessions]
    drawn = figures.Drawn(max_points)
    given = comparison.get("origins_ns") or {}
    origins = [given.get(label) for label in labels]  # the comparison's session time
    rows = figures.overlay([session_panels(data, origin)
                            for data, origin in zip(sessions, origins, strict=True)])
    signal_rows, undrawn = _signal_rows(sessions, origins, comparison, signals)
    rows += signal_rows
    title = (f"hil comparison: {os.path.basename(sessions[1].path)} against "
             f"{os.path.basename(sessions[0].path)}")
    passed = comparison.get("passed")
    verdict = badge(None if passed is None else bool(passed),
                    "no verdict" if passed is None else "PASSED" if passed else "FAILED")
    facts = ", ".join(f"{key} {comparison[key]}" for key in ("application", "alignment")
                      if comparison.get(key))
    head = [f"<h1>{html.escape(title)}</h1>",
            f"<p>{verdict} {html.escape(facts)}</p>",
            f"<p>baseline {html.escape(sessions[0].path)}<br>candidate "
            f"{html.escape(sessions[1].path)}</p>",
            *(paragraph(f"Not drawn: {why}", "note") for why in undrawn)]
    return _write(out_path, title, head, sessions, summaries, labels, rows,
                  sections.comparison_rows(comparison), drawn)


def _write(out_path: str, title: str, head: list[str], sessions: Sequence[SessionData],
           summaries: Sequence[Mapping[str, Any]], labels: Sequence[str],
           rows: list[figures.Row], comparison: str, drawn: figures.Drawn) -> HtmlStats:
    import plotly.io as pio
    from plotly.offline import get_plotlyjs

    plots = [figures.time_figure(rows, labels, drawn)] if rows else []
    histogram = figures.tick_histogram(sessions, labels)
    divs = [pio.to_html(fig, full_html=False, include_plotlyjs=False, config=PLOT_CONFIG,
                        div_id=f"plot-{n}") for n, fig in enumerate([*plots, histogram])
            if fig is not None]
    signals = section("Signals", *divs[:len(plots)],
                      anchor="signals") if plots else ""
    body = [*head, _decimation_note(drawn), sections.damage(summaries, labels), comparison,
            signals, sections.kpis(summaries, labels), sections.events(sessions, labels),
            sections.loop(summaries, labels, "".join(divs[len(plots):])),
            sections.kind_sections(summaries, labels),
            sections.metadata(sessions, summaries, labels)]
    page = document(title, [part for part in body if part], get_plotlyjs())
    folder = os.path.dirname(out_path)
    if folder:
        os.makedirs(folder, exist_ok=True)
    with open(out_path, "w", encoding="utf-8") as out:
        out.write(page)
    return HtmlStats(out_path, os.path.getsize(out_path), len(divs), drawn.traces,
                     drawn.points, tuple(drawn.decimated), drawn.max_points)


def _signal_rows(sessions: Sequence[SessionData], origins: Sequence[int | None],
                 comparison: Mapping[str, Any],
                 signals: Sequence[str]) -> tuple[list[figures.Row], list[str]]:
    """A row per signal asked for (unknown: a UsageError) and per signal row of the
    comparison, its worst point marked; and why a signal row the sessions lack is not
    drawn."""
    worst = {str(r.get("name")): r for r in comparison.get("rows", [])
             if r.get("kind") == "signal"}
    rows, undrawn = [], []
    for name in dict.fromkeys([*signals, *worst]):
        try:
            traces = [signal_trace(data, name, name.rpartition(":")[2], origin)
                      for data, origin in zip(sessions, origins, strict=True)]
        except UsageError as error:
            if name in signals:
                raise
            undrawn.append(str(error))
            continue
        found = worst.get(name, {})
        starts = found.get("from_start_deg")  # a position compared from each run's start
        if starts:
            traces = [replace(trace, y=trace.y - start)
                      for trace, start in zip(traces, starts, strict=True)]
        field = name.rpartition(":")[2]
        unit = unit_of(field)
        title = f"{name} (from start)" if starts else name
        row = figures.Row(Panel(title, f"{field} [{unit}]" if unit else field, tuple(traces)),
                          list(enumerate(traces)))
        if found.get("worst_t_s") is not None:
            candidate = found.get("candidate")
            row.marks.append(figures.Mark(
                float(found["worst_t_s"]), None if candidate is None else float(candidate),
                f"worst: difference {text(found.get('difference'))} at "
                f"{text(float(found['worst_t_s']))} s"))
        rows.append(row)
    return rows, undrawn


def _check_points(max_points: int) -> None:
    if isinstance(max_points, bool) or not isinstance(max_points, int) or max_points < 2:
        raise UsageError(f"max_points: expected an integer of at least 2 (points per trace), "
                         f"got {max_points!r}")


def _decimation_note(drawn: figures.Drawn) -> str:
    if not drawn.decimated:
        return ""
    return paragraph(
        f"Decimated for size: {len(drawn.decimated)} of {drawn.traces} traces are drawn "
        f"with at most {drawn.max_points} points each (the smallest and largest sample of "
        "each interval, so every peak shows); the session file holds every sample. "
        f"Decimated: {', '.join(drawn.decimated)}.", "note")


def _session_badge(kpis: Mapping[str, Any]) -> str:
    passed, status = kpis.get("passed"), kpis.get("status")
    if passed is None and status in (None, "completed"):
        return badge(None, status or "no verdict")
    ok = passed is not False and status in (None, "completed")
    return badge(ok, f"{'PASSED' if ok else 'FAILED'}{f' ({status})' if status else ''}")


def _headline(summary: Mapping[str, Any]) -> str:
    kpis = summary["kpis"]
    words = [summary["kind"] or "session", f"{summary['duration_s']:.3f} s",
             f"clock {summary['clock'] or '?'}"]
    if kpis.get("controller"):
        words.append(f"controller {kpis['controller']}")
    return ", ".join(words)
