"""The report's plotly figures: the panels of one session, or of two overlaid (baseline
dotted, candidate solid) with the compared signals and their worst points, and the loop's
step-time histogram. Every trace is drawn with at most ``max_points`` points."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil.core.html_report.decimate import minmax_decimate
from hil.core.html_report.panels import Panel, Trace
from hil.core.recording.reader import SessionData
from hil.core.report import tick_samples

# plotly's own colour cycle; a trace keeps its colour in both sessions of a comparison
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
           "#7f7f7f", "#bcbd22", "#17becf")
ROW_PX = 240
HISTOGRAM_BINS = 60


@dataclass
class Drawn:
    """What the figures hold: traces, points, and the traces that were decimated."""

    max_points: int
    traces: int = 0
    points: int = 0
    decimated: list[str] = field(default_factory=list)

    def line(self, trace: Trace, label: str) -> tuple[np.ndarray, np.ndarray]:
        """The trace's points to draw, decimated to ``max_points`` (and counted); a step
        trace first keeps only its changes, which draws it exactly."""
        t, y = trace.t_s, trace.y
        if trace.step and y.size > 2:
            changes = np.flatnonzero(np.diff(y)) + 1
            keep = np.unique(np.concatenate([[0], changes, [y.size - 1]]))
            t, y = t[keep], y[keep]
        kept = y.size
        t, y = minmax_decimate(t, y, self.max_points)
        self.traces += 1
        self.points += int(y.size)
        if y.size < kept:
            self.decimated.append(label)
        return t, y


@dataclass(frozen=True)
class Mark:
    """A point to point out: the worst excursion of a compared signal."""

    t_s: float
    y: float | None
    label: str


@dataclass
class Row:
    """One row of a time figure: a panel as the sessions drew it (``series``: session index
    and trace), with marks."""

    panel: Panel
    series: list[tuple[int, Trace]]
    marks: list[Mark] = field(default_factory=list)


def overlay(sessions: Sequence[list[Panel]]) -> list[Row]:
    """The rows of one session's panels, or of several sessions' panels matched by title
    (a panel one session lacks is drawn from the other)."""
    rows: dict[str, Row] = {}
    for index, panels in enumerate(sessions):
        for panel in panels:
            row = rows.setdefault(panel.title, Row(panel, []))
            if index:  # the lines (limits) are the last session's
                row.panel = panel
            row.series.extend((index, trace) for trace in panel.traces)
    return list(rows.values())


def time_figure(rows: Sequence[Row], labels: Sequence[str], drawn: Drawn) -> Any:
    """The rows stacked on one shared time axis, one legend per row."""
    from plotly.subplots import make_subplots

    fig = make_subplots(rows=len(rows), cols=1, shared_xaxes=True,
                        vertical_spacing=min(0.08, 0.35 / len(rows)),
                        subplot_titles=[row.panel.title for row in rows])
    for i, row in enumerate(rows, start=1):
        legend = "legend" if i == 1 else f"legend{i}"
        _draw_row(fig, i, row, labels, legend, drawn)
        domain = fig.layout["yaxis" if i == 1 else f"yaxis{i}"].domain
        fig.layout[legend] = {"x": 1.01, "xanchor": "left", "y": domain[1], "yanchor": "top",
                              "font": {"size": 10}}
    fig.update_xaxes(title_text="time [s]", row=len(rows), col=1)
    fig.update_layout(height=80 + ROW_PX * len(rows), template="plotly_white",
                      margin={"l": 70, "r": 20, "t": 40, "b": 50}, hovermode="x")
    return fig


def _draw_row(fig: Any, i: int, row: Row, labels: Sequence[str], legend: str,
              drawn: Drawn) -> None:
    import plotly.graph_objects as go

    colours: dict[str, str] = {}
    for session, trace in row.series:
        colour = colours.setdefault(trace.name, "#444444" if trace.dash
                                    else PALETTE[len(colours) % len(PALETTE)])
        name = f"{trace.name} ({labels[session]})" if len(labels) > 1 else trace.name
        t, y = drawn.line(trace, f"{row.panel.title}: {name}")
        baseline = len(labels) > 1 and session == 0
        dash = "dot" if baseline else "dash" if trace.dash else "solid"
        fig.add_trace(go.Scatter(
            x=t, y=y, name=name, mode="lines", legend=legend, opacity=0.75 if baseline else 1,
            line={"color": colour, "width": 1.2, "dash": dash,
                  "shape": "hv" if trace.step else "linear"}), row=i, col=1)
    for value, label in row.panel.lines:
        fig.add_hline(y=value, row=i, col=1, line={"color": "#d62728", "width": 1,
                                                   "dash": "dot"},
                      annotation_text=label, annotation_font_size=9)
    for mark in row.marks:
        fig.add_vline(x=mark.t_s, row=i, col=1, line={"color": "#d62728", "width": 1})
        if mark.y is not None:
            fig.add_trace(go.Scatter(x=[mark.t_s], y=[mark.y], name=mark.label,
                                     mode="markers", legend=legend,
                                     marker={"symbol": "x", "size": 11, "color": "#d62728"}),
                          row=i, col=1)
    fig.update_yaxes(title_text=row.panel.y_label, row=i, col=1)
    if row.panel.ticks:
        fig.update_yaxes(tickvals=[v for v, _ in row.panel.ticks],
                         ticktext=[t for _, t in row.panel.ticks], row=i, col=1)


def tick_histogram(sessions: Sequence[SessionData], labels: Sequence[str]) -> Any | None:
    """Runs per tick-time bin (log bins, us: a task's run in a tick, every phase) of every
    loop task, as step lines; None without any timing recorded."""
    import plotly.graph_objects as go

    samples = [(index, topic[len("/loop/"):-len("/timing")], tick_samples(
        [m for _, m in data.topic(topic) if isinstance(m, dict)]))
        for index, data in enumerate(sessions) for topic in sorted(data.messages)
        if topic.startswith("/loop/") and topic.endswith("/timing")]
    samples = [(index, task, s) for index, task, s in samples if s.size]
    if not samples:
        return None
    top = max(float(s.max()) for _, _, s in samples)
    low = min(max(float(s.min()), 0.1) for _, _, s in samples)
    edges = np.geomspace(low, max(top, low * 10), HISTOGRAM_BINS + 1)
    fig = go.Figure()
    colours: dict[str, str] = {}
    for index, task, s in samples:
        counts, _ = np.histogram(np.clip(s, edges[0], edges[-1]), edges)
        colour = colours.setdefault(task, PALETTE[len(colours) % len(PALETTE)])
        baseline = len(labels) > 1 and index == 0
        fig.add_trace(go.Scatter(
            x=edges, y=np.append(counts, counts[-1]).astype(float),
            name=f"{task} ({labels[index]})" if len(labels) > 1 else task, mode="lines",
            line={"shape": "hv", "color": colour, "width": 1.2,
                  "dash": "dot" if baseline else "solid"}))
    fig.update_xaxes(type="log", title_text="tick time (the task's run, all phases) [us]")
    fig.update_yaxes(type="log", title_text="runs")
    fig.update_layout(height=320, template="plotly_white", title="loop tick time per task",
                      margin={"l": 70, "r": 20, "t": 40, "b": 50})
    return fig
