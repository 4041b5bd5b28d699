"""Summaries and plots of recorded sessions (any session, truncated ones included)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from hil.core.kpi_text import kpi_rows, value_text
from hil.core.loop import PHASES
from hil.core.plugins import registered
from hil.core.recording.reader import SessionData
from hil.core.stats import percentile_summary
from hil.core.verdict import UNSAFE_EVENTS

# Plotters of the applications, keyed by the session kind recorded in the metadata. An
# application (or a user's package) registers ``kind = "module:function"`` in this entry-point
# group; the framework names none of them and imports one only when such a session is drawn.
PLOTTER_GROUP = "hil.plotters"
Plotter = Callable[[SessionData, str], None]
# Kind-specific sections of ``hil report`` (text and ``--json``), the same way: ``kind =
# "module:Object"``, the object having ``key`` (its JSON key), ``section(data) -> dict`` (empty
# when the session has nothing to show) and ``lines(section) -> list[str]`` (its text).
SUMMARY_GROUP = "hil.summaries"


class KindSummary(Protocol):
    key: str

    def section(self, data: SessionData) -> dict[str, Any]: ...

    def lines(self, section: dict[str, Any]) -> list[str]: ...


def find_plotter(kind: str) -> Plotter | None:
    """The plotter registered for sessions of ``kind``, or None."""
    plotter: Plotter | None = registered(PLOTTER_GROUP, kind)
    return plotter


def find_summary(kind: str) -> KindSummary | None:
    """The report section registered for sessions of ``kind``, or None."""
    summary: KindSummary | None = registered(SUMMARY_GROUP, kind)
    return summary


def loop_stats(data: SessionData) -> dict[str, Any]:
    """Per-task timing from the ``/loop/<task>/timing`` topics (exact over what was recorded):
    lateness, ``tick_us`` (the task's whole run in a tick, every phase: not the controller's
    step, the KPI ``step_us``) and ``<phase>_us`` for each phase it took part in. A session
    recorded before the loop had phases timed the whole run as ``compute_us``: it reports as
    ``tick_us``."""
    out: dict[str, Any] = {}
    for topic in data.messages:
        if not (topic.startswith("/loop/") and topic.endswith("/timing")):
            continue
        msgs = [m for _, m in data.topic(topic) if isinstance(m, dict)]
        if not msgs:
            continue
        stats: dict[str, Any] = {
            "period_s": msgs[0].get("period_s"),
            "runs": int(sum(m.get("runs", 0) for m in msgs)),
            "missed": int(sum(m.get("missed", 0) for m in msgs)),
            "overruns": int(sum(m.get("overruns", 0) for m in msgs)),
            "lateness_us": percentile_summary(_samples(msgs, "lateness_us")),
        }
        stats["tick_us"] = percentile_summary(tick_samples(msgs))
        if any(f"{phase}_us" in msgs[0] for phase in PHASES if phase != "compute"):
            phases = {phase: _samples(msgs, f"{phase}_us") for phase in PHASES}
            stats.update({f"{phase}_us": percentile_summary(v) for phase, v in phases.items()
                          if v.size})
        out[topic[len("/loop/"):-len("/timing")]] = stats
    return out


def tick_samples(messages: list[dict[str, Any]]) -> np.ndarray:
    """Every recorded run's ``tick_us`` (the sum of its phases) from a task's timing
    messages; a session recorded before the loop had phases: its ``compute_us``."""
    if not messages or not any(f"{phase}_us" in messages[0] for phase in PHASES
                               if phase != "compute"):
        return _samples(messages, "compute_us")
    taken = [v for v in (_samples(messages, f"{phase}_us") for phase in PHASES) if v.size]
    return np.asarray(np.sum(taken, axis=0), float) if taken else np.empty(0)


def _samples(messages: list[dict[str, Any]], key: str) -> np.ndarray:
    return np.concatenate([np.asarray(m.get(key, []), float) for m in messages] or
                          [np.empty(0)])


def realtime_helpers(data: SessionData) -> dict[str, dict[str, str]]:
    """What each process standing in for hardware (an emulator) was granted: the session's
    ``realtime.<helper>`` metadata, by helper (``{"emulator": {"pid": ..., step: ...}}``)."""
    return {name.removeprefix("realtime."): dict(record)
            for name, record in sorted(data.metadata.items())
            if name.startswith("realtime.")}


def session_kind(data: SessionData) -> str:
    return data.metadata.get("session", {}).get("kind", "")


def kpis(data: SessionData) -> dict[str, Any]:
    raw = data.metadata.get("kpis", {}).get("json")
    try:
        return json.loads(raw) if raw else {}
    except ValueError:
        return {}


def summarize(data: SessionData) -> dict[str, Any]:
    """The ``hil report --json`` document."""
    events = [m for _, m in data.topic("/events") if isinstance(m, dict)]
    summary = {
        "file": data.path,
        "kind": session_kind(data),
        "clock": data.metadata.get("session", {}).get("clock", ""),
        "topics": data.topic_counts,
        "duration_s": round(data.duration_s(), 6),
        "files": data.files,
        "encodings": dict(sorted(data.encodings.items())),
        "recovered": data.recovered,
        "lost_bytes": data.lost_bytes,
        "lost_messages": data.lost_messages,
        "damage": [d.as_dict() for d in data.damage],
        "ended": data.metadata.get("recorder", {}).get("ended", ""),
        "dropped": json.loads(data.metadata.get("recorder", {}).get("dropped", "{}")),
        "loop": loop_stats(data),
        "realtime": data.metadata.get("realtime", {}),
        "realtime_helpers": realtime_helpers(data),
        "events": {
            level: sum(1 for e in events if e.get("level") == level)
            for level in ("info", "warning", "error")
        },
        "unsafe": [str(e.get("message")) for e in events if e.get("kind") in UNSAFE_EVENTS],
        "params": param_changes(events),
        "kpis": kpis(data),
    }
    extra = find_summary(session_kind(data))
    if extra is not None and (section := extra.section(data)):
        summary[extra.key] = section
    return summary


def param_changes(events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The parameters changed while the run ran, and the refused requests, in order (the
    ``param.changed`` and ``param.refused`` events of :mod:`hil.core.tuning`)."""
    changes = []
    for event in events:
        kind, data = event.get("kind"), event.get("data") or {}
        if kind in ("param.changed", "param.refused"):
            changes.append({"accepted": kind == "param.changed",
                            **{k: data.get(k) for k in ("parameter", "old", "new", "value",
                                                        "client", "tick", "reason")
                               if k in data}})
    return changes


def _param_lines(changes: list[dict[str, Any]]) -> list[str]:
    lines = ["params   changed while running"] if changes else []
    for change in changes:
        if change["accepted"]:
            lines.append(f"  {change.get('parameter')}: {_param(change.get('old'))} -> "
                         f"{_param(change.get('new'))} at tick {change.get('tick')} "
                         f"({change.get('client')})")
        else:
            lines.append(f"  {change.get('parameter')} = {_param(change.get('value'))} "
                         "refused "
                         f"({change.get('client')}): {change.get('reason')}")
    return lines


def _param(value: Any) -> str:
    """A parameter's value as it was set (a gain to six digits: 3.6111), not a repr."""
    return f"{value:g}" if isinstance(value, float) else value_text(value)


def format_summary(summary: dict[str, Any]) -> str:
    """Human-readable text of :func:`summarize`."""
    lines = [f"session  {summary['file']}"]
    kind = summary["kind"] or "unknown kind"
    lines.append(f"kind     {kind}, clock {summary['clock'] or '?'}, "
                 f"duration {summary['duration_s']:.3f} s")
    if len(summary["files"]) > 1:
        lines.append(f"files    {len(summary['files'])} (split series): "
                     f"{os.path.basename(summary['files'][0])} ... "
                     f"{os.path.basename(summary['files'][-1])}")
    lines.extend(_damage_lines(summary))
    lines.extend(f"UNSAFE: {line}" for line in summary["unsafe"])
    if summary["ended"]:
        lines.append(f"ENDED ABNORMALLY: {summary['ended']}")
    if summary["dropped"]:
        lines.append("DROPPED by the recorder: " + ", ".join(
            f"{topic} {count}" for topic, count in summary["dropped"].items()))
    lines.append("topics")
    for topic, count in summary["topics"].items():
        lines.append(f"  {topic:<32} {count:>9} msgs")
    if summary["loop"]:
        lines.append("loop timing           runs   missed  overruns   lateness p50/p99/max us"
                     "   tick p50/p99/max us")
        for task, s in summary["loop"].items():
            lat, tick = s["lateness_us"], s["tick_us"]
            lines.append(
                f"  {task:<16} {s['runs']:>9} {s['missed']:>8} {s['overruns']:>9}   "
                f"{lat['p50']:>8.1f}/{lat['p99']:.1f}/{lat['max']:.1f}"
                f"   {tick['p50']:>8.1f}/{tick['p99']:.1f}/{tick['max']:.1f}"
            )
            phases = [f"{phase} {s[f'{phase}_us']['p50']:.1f}/{s[f'{phase}_us']['p99']:.1f}"
                      for phase in PHASES if f"{phase}_us" in s]
            if phases:
                lines.append(f"  {'':<16} phases p50/p99 us: " + ", ".join(phases))
    if summary["realtime"]:
        lines.append("real-time hardening")
        for step, outcome in summary["realtime"].items():
            lines.append(f"  {step:<16} {outcome}")
    for helper, steps in summary["realtime_helpers"].items():
        steps = dict(steps)
        lines.append(f"real-time hardening of the {helper} (process {steps.pop('pid', '?')})")
        for step, outcome in steps.items():
            lines.append(f"  {step:<16} {outcome}")
    ev = summary["events"]
    lines.append(f"events   {ev['info']} info, {ev['warning']} warning, {ev['error']} error")
    lines.extend(_param_lines(summary.get("params", [])))
    if summary["kpis"]:
        lines.append("kpis")
        lines += [f"  {name:<24} {text}" for name, text in kpi_rows(summary["kpis"])]
    extra = find_summary(summary["kind"])
    if extra is not None and extra.key in summary:
        lines.extend(extra.lines(summary[extra.key]))
    return "\n".join(lines)


def _damage_lines(summary: dict[str, Any]) -> list[str]:
    if not summary["damage"]:
        return ["RECOVERED: the file was not finished"] if summary["recovered"] else []
    lost = summary["lost_messages"]
    lines = [f"DAMAGED: {summary['lost_bytes']} byte(s) unreadable, "
             f"{'an unknown number of' if lost is None else lost} message(s) lost"]
    for d in summary["damage"]:
        where = f"from byte {d['offset']}"
        if "start_ns" in d:
            where += f", log time {d['start_ns'] / 1e9:.3f}..{d['end_ns'] / 1e9:.3f} s"
        count = f"{d['messages']} message(s)" if "messages" in d else "messages unknown"
        lines.append(f"  {d['kind']:<10} {d['bytes']} byte(s) {where}: {count}"
                     + (f" ({d['reason']})" if d.get("reason") else ""))
    return lines


#: the height of one row of a PNG's KPI table [inches]: a line of 8 pt text
KPI_ROW_IN = 0.19


def kpi_table_rows(data: SessionData) -> list[list[str]]:
    """The session's KPIs as a PNG's table rows (name, text), the session's file left out."""
    return [[name, text] for name, text in kpi_rows(kpis(data)) if name != "mcap"]


def kpi_table(ax: Any, rows: list[list[str]]) -> None:
    """``rows`` as the KPI table of a report PNG, filling ``ax`` (its height:
    :data:`KPI_ROW_IN` a row, and one for the header)."""
    ax.axis("off")
    if rows:
        cell = ax.table(cellText=rows, colLabels=["KPI", "value"], loc="upper center",
                        colWidths=[0.3, 0.65], cellLoc="left")
        cell.auto_set_font_size(False)
        cell.set_fontsize(8)


def plot_loop_timing(data: SessionData, out_png: str) -> None:
    """Default plot: lateness and compute time of every loop task over the session."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = [t for t in data.messages if t.startswith("/loop/")]
    fig, axes = plt.subplots(max(1, len(tasks)), 1, figsize=(10, 2.6 * max(1, len(tasks))),
                             squeeze=False)
    for ax, topic in zip(axes[:, 0], tasks, strict=False):
        msgs = data.topic(topic)
        messages = [m for _, m in msgs]
        ax.plot(_samples(messages, "lateness_us"), lw=0.6, label="lateness [us]")
        for phase in PHASES:
            samples = _samples(messages, f"{phase}_us")
            if samples.size:
                ax.plot(samples, lw=0.6, label=f"{phase} [us]")
        ax.set_title(topic)
        ax.set_xlabel("run")
        ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(out_png, dpi=110)
    plt.close(fig)


def plot_session(data: SessionData, out_png: str) -> None:
    """Draw the session with its kind's plotter, or the loop timing when there is none."""
    (find_plotter(session_kind(data)) or plot_loop_timing)(data, out_png)
