"""``hil report`` for servo sessions: the feedback section (who was late when feedback was
stale) and the plot (``--out F.png``): tracking, error, current, prediction waterfall.

The feedback section (:class:`FeedbackTiming`, JSON key ``feedback``), per axis: the cycles
without fresh feedback and their share, the longest run of them, the SYNC-to-reply time of
the fresh ones, the loop's lateness, and which side was late (:func:`~hil.servo.safety.
judge_stale`) over the whole session and over its worst safety window (``stale_window_ms``,
the window the safety net counts in). A tick's lateness is taken from its stamps (the tick's
start against the schedule grid, the least late tick as the grid's origin), so a recording
that dropped messages is judged on what it kept.

The waterfall is drawn like the servo paper's Figs. 9-10: a thin line per recorded tick k for
the predicted inputs û(k+i|k), i = 0..H_u-1, over the applied current (thick). It shows a
window of ``WATERFALL_TICKS`` recorded predictions centred on the largest change of the
commanded current after the first tenth of the session (past the start-up transient), where
the predictions have something to show.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

import numpy as np

from hil.controllers.servo.model import SAMPLE_PERIOD_S
from hil.core.recording.reader import SessionData
from hil.core.report import KPI_ROW_IN, kpi_table, kpi_table_rows, kpis
from hil.servo.safety import ServoSafety, judge_stale

WATERFALL_TICKS = 100


class FeedbackTiming:
    """The ``feedback`` section of ``hil report`` (entry point ``hil.summaries``)."""

    key = "feedback"

    def section(self, data: SessionData) -> dict[str, Any]:
        """Per feedback topic (``/drive/feedback``, ``/axis/NAME/feedback``): stale cycles,
        reply times, the loop's lateness and the late side (empty without feedback)."""
        period_s = float(data.metadata.get("session", {}).get("base_period_s", 0) or 0)
        window_ms = _stale_window_ms(data)
        info = kpis(data)
        out = {}
        for topic, late_frames in _feedback_topics(data, info):
            row = feedback_timing(data, topic, period_s, window_ms)
            if row:
                if late_frames is not None:
                    row["late_frames"] = late_frames
                out[topic] = row
        return out

    def lines(self, section: dict[str, Any]) -> list[str]:
        """Per topic: the stale share and who was late, then the worst window."""
        out = []
        for topic, row in section.items():
            rtt = row["rtt_us"]
            out.append(f"feedback {topic}: {row['stale']} of {row['cycles']} cycles stale "
                       f"({100 * row['stale_share']:.2f} %, longest run "
                       f"{row['longest_stale_run']}); SYNC to reply read p50/p99/max "
                       f"{rtt['p50']:.0f}/{rtt['p99']:.0f}/{rtt['max']:.0f} us"
                       + (f"; {row['late_frames']} late frames" if "late_frames" in row
                          else ""))
            out.append(f"  late side: {row['late_side']}: {row['verdict']}")
            worst = row["worst_window"]
            if worst["stale"]:
                out.append(f"  worst {worst['window_ms']:g} ms window, from t={worst['t_s']:.3f} "
                           f"s: {worst['stale']} of {worst['cycles']} cycles stale, late side "
                           f"{worst['late_side']}: {worst['verdict']}")
        return out


FEEDBACK_TIMING = FeedbackTiming()


def _stale_window_ms(data: SessionData) -> float:
    """The safety net's stale window of the session (its drive config), else the default."""
    try:
        config = json.loads(data.metadata.get("config", {}).get("json", "{}"))
        return float(config["drive"]["safety"]["stale_window_ms"])
    except (ValueError, KeyError, TypeError):
        return ServoSafety().stale_window_ms


def _feedback_topics(data: SessionData, info: dict[str, Any]
                     ) -> list[tuple[str, int | None]]:
    """The session's feedback topics, each with the late frames its KPIs counted (if any)."""
    names = axis_names(data)
    if not names:
        late = info.get("faults", {}).get("late_frames") if isinstance(info.get("faults"),
                                                                       dict) else None
        return [("/drive/feedback", late)]
    axes = info.get("axes", {}) if isinstance(info.get("axes"), dict) else {}
    return [(f"/axis/{name}/feedback", axes.get(name, {}).get("late_frames")) for name in names]


def feedback_timing(data: SessionData, topic: str, period_s: float,
                    window_ms: float) -> dict[str, Any]:
    """The feedback section of one topic (empty without feedback, or without the commands
    that give each tick its slot on the schedule grid, or in a session that keeps only some
    of their fields: a baseline's)."""
    feedback = data.arrays(topic)
    command = data.arrays(topic.removesuffix("/feedback") + "/command")
    if feedback["log_time_ns"].size == 0 or command["log_time_ns"].size == 0 or period_s <= 0 \
            or "t_s" not in command or not {"fresh", "rtt_us"} <= feedback.keys():
        return {}
    # each tick's slot: the t_s of the /drive/command stamped with the same tick start
    order = np.argsort(command["log_time_ns"], kind="stable")
    command_ns = command["log_time_ns"][order].astype(np.int64)
    feedback_ns = feedback["log_time_ns"].astype(np.int64)
    at = np.minimum(np.searchsorted(command_ns, feedback_ns), command_ns.size - 1)
    keep = command_ns[at] == feedback_ns
    if not keep.any():
        return {}
    stamps = feedback_ns[keep]
    slots = np.rint(command["t_s"][order][at[keep]] / period_s).astype(np.int64)
    period_ns = round(period_s * 1e9)
    offsets = stamps - slots * period_ns
    late_us = (offsets - offsets.min()) / 1e3
    stale = ~feedback["fresh"][keep].astype(bool)
    rtt = feedback["rtt_us"][keep].astype(float)
    fresh_rtt = rtt[~stale]
    whole = judge_stale(stale, late_us, rtt, period_s, slots)
    return {
        "cycles": int(stale.size), "stale": int(stale.sum()),
        "stale_share": round(float(stale.mean()), 6),
        "longest_stale_run": _longest_run(stale),
        "rtt_us": _percentiles(fresh_rtt),
        "loop_lateness_us": _percentiles(late_us),
        "skipped_ticks": _skipped(slots),
        "late_side": whole.side, "verdict": whole.describe(),
        "worst_window": _worst_window(stale, late_us, rtt, slots, period_s, window_ms),
    }


def _percentiles(values: np.ndarray) -> dict[str, float]:
    if values.size == 0:
        return {"p50": 0.0, "p99": 0.0, "max": 0.0}
    return {"p50": round(float(np.percentile(values, 50)), 1),
            "p99": round(float(np.percentile(values, 99)), 1),
            "max": round(float(values.max()), 1)}


def _skipped(slots: np.ndarray) -> int:
    return int(slots[-1] - slots[0] + 1 - slots.size) if slots.size else 0


def _longest_run(flags: np.ndarray) -> int:
    edges = np.diff(np.concatenate(([0], flags.astype(np.int8), [0])))
    return int((np.flatnonzero(edges < 0) - np.flatnonzero(edges > 0)).max(initial=0))


def _worst_window(stale: np.ndarray, late_us: np.ndarray, rtt: np.ndarray, slots: np.ndarray,
                  period_s: float, window_ms: float) -> dict[str, Any]:
    """The safety net's window (``window_ms`` of cycles) with the most stale cycles, judged."""
    size = min(stale.size, max(1, round(window_ms / 1000 / period_s)))
    sums = np.concatenate(([0], np.cumsum(stale, dtype=np.int64)))
    counts = sums[size:] - sums[:-size]  # each window's stale cycles, as a convolution counts
    start = int(np.argmax(counts))
    part = slice(start, start + size)
    verdict = judge_stale(stale[part], late_us[part], rtt[part], period_s, slots[part])
    return {"window_ms": window_ms, "t_s": round(float(slots[start] * period_s), 4),
            "cycles": size, "stale": int(counts[start]), "late_side": verdict.side,
            "verdict": verdict.describe()}


def _seconds(stamps_ns: np.ndarray, origin_ns: int) -> np.ndarray:
    return (stamps_ns - origin_ns) / 1e9


def current_limit(data: SessionData) -> float | None:
    """The run's current limit [mA] (the ``umax_mA`` KPI, else the configured ``umax``)."""
    limit = kpis(data).get("umax_mA")
    if limit is None:
        try:
            config = json.loads(data.metadata.get("config", {}).get("json", "{}"))
            limit = config.get("servo", {}).get("umax")
        except ValueError:
            return None
    return float(limit) if limit is not None else None


def waterfall_window(command_ma: np.ndarray, stamps_ns: np.ndarray,
                     prediction_ns: np.ndarray, width: int = WATERFALL_TICKS) -> slice:
    """The recorded predictions to draw: ``width`` of them around the largest |Δu|."""
    if prediction_ns.size <= width or command_ma.size < 2:
        return slice(0, prediction_ns.size)
    skip = command_ma.size // 10  # not the start-up transient
    jump = skip + int(np.argmax(np.abs(np.diff(command_ma[skip:])))) + 1
    centre = int(np.searchsorted(prediction_ns, stamps_ns[jump]))
    start = min(max(0, centre - width // 2), prediction_ns.size - width)
    return slice(start, start + width)


def plot_servo(data: SessionData, out_png: str) -> None:
    """Reference and position, tracking error, commanded and measured current, and (MPC) the
    waterfall of predicted inputs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes_names = axis_names(data)
    if axes_names:
        plot_axes(data, axes_names, out_png)
        return
    command = data.arrays("/drive/command")
    feedback = data.arrays("/drive/feedback")
    prediction = data.arrays("/mpc/prediction")
    stamps = command["log_time_ns"]
    if stamps.size == 0:
        fig, ax = plt.subplots(figsize=(8, 2))
        ax.text(0.5, 0.5, "no /drive/command messages recorded", ha="center", va="center")
        ax.set_axis_off()
        fig.savefig(out_png, dpi=110)
        plt.close(fig)
        return
    origin = int(stamps[0])
    t = _seconds(stamps, origin)
    has_prediction = "u_mA" in prediction and prediction["log_time_ns"].size > 0
    plots = 4 if has_prediction else 3
    table = kpi_table_rows(data)
    table_in = KPI_ROW_IN * (len(table) + 1)
    fig, axes = plt.subplots(plots + 1, 1, figsize=(10, 2.6 * plots + table_in),
                             gridspec_kw={"height_ratios": [2.6] * plots + [table_in]})
    info = kpis(data)
    title = f"servo session: {info.get('controller', '?')}, {info.get('reference', '')}"
    fig.suptitle(title, fontsize=10)
    settle_s = float(info.get("settle_s") or 0.0)

    reference, error = command["reference_deg"], command["error_deg"]
    ax = axes[0]
    ax.plot(t, reference, "k--", lw=1.0, label="reference")
    ax.plot(t, reference + error, lw=1.0, label="position")
    ax.set_ylabel("angle [deg]")
    ax.set_title("tracking", fontsize=9)
    ax.legend(loc="best", fontsize=8)

    draw_error(axes[1], t, error, settle_s)

    ax = axes[2]
    ax.plot(t, command["command_mA"], lw=0.9, label="commanded")
    if feedback["log_time_ns"].size:
        ax.plot(_seconds(feedback["log_time_ns"], origin), feedback["current_mA"], lw=0.7,
                alpha=0.8, label="drive (torque actual)")
    limit = current_limit(data)
    if limit is not None:
        for sign in (1, -1):
            ax.axhline(sign * limit, color="r", lw=0.6, ls=":",
                       label=f"current limit ±{limit:g} mA" if sign > 0 else None)
    ax.set_ylabel("current [mA]")
    ax.set_title("motor current", fontsize=9)
    ax.legend(loc="best", fontsize=8)

    if has_prediction:
        draw_waterfall(axes[3], command, prediction, origin)
    for ax in axes[:plots]:
        mark_settle(ax, settle_s)
    axes[plots - 1].set_xlabel("time [s]")
    kpi_table(axes[plots], table)
    fig.tight_layout()
    fig.savefig(out_png, dpi=110)
    plt.close(fig)


#: the share of a run at its start whose transient the error axis leaves off its scale
START_SHARE = 0.05


def error_scale(t: np.ndarray, error: np.ndarray, settle_s: float) -> tuple[float, float]:
    """The error axis' half-height [deg]: the largest error after the start (the settle
    window, else the first :data:`START_SHARE` of the run) with a margin, so a start
    transient does not flatten the rest; and from when it counts [s]."""
    start = max(settle_s, float(t[0] + START_SHARE * (t[-1] - t[0]))) if t.size else 0.0
    after = np.abs(error[(t >= start) & np.isfinite(error)])
    if after.size == 0 or not after.max() > 0:
        return 0.0, start
    return 1.15 * float(after.max()), start


def draw_error(ax: Any, t: np.ndarray, error: np.ndarray, settle_s: float) -> None:
    """The tracking error, scaled to what follows the start (:func:`error_scale`); the start
    transient, when it goes beyond, clipped and said so."""
    ax.plot(t, error, lw=0.8)
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_ylabel("error [deg]")
    title = "tracking error (position - reference)"
    half, start = error_scale(t, error, settle_s)
    before = np.abs(error[t < start])
    if half > 0 and before.size and before.max() > half:
        ax.set_ylim(-half, half)
        title += f"; off scale before t = {start:.3g} s: up to {before.max():.3g} deg"
    ax.set_title(title, fontsize=9)


def mark_settle(ax: Any, settle_s: float) -> None:
    """The settle window (``--settle``: the start the KPIs leave out), shaded, in the
    legend."""
    if settle_s <= 0:
        return
    ax.axvspan(0.0, settle_s, color="0.85", zorder=0,
               label=f"settle {settle_s:g} s: not in the KPIs")
    ax.legend(loc="best", fontsize=8)


def draw_waterfall(ax: Any, command: Mapping[str, np.ndarray],
                   prediction: Mapping[str, np.ndarray], origin: int) -> None:
    """Thin lines: û(k+i|k) of each recorded tick in the window; thick: the applied current."""
    stamps = prediction["log_time_ns"]
    window = waterfall_window(command["command_mA"], command["log_time_ns"], stamps)
    inputs = prediction["u_mA"][window]
    starts = _seconds(stamps[window], origin)
    if inputs.dtype == object or inputs.ndim != 2:  # ragged: one line per message
        rows = [np.asarray(u, float) for u in inputs]
    else:
        rows = list(inputs)
    for t0, u in zip(starts, rows, strict=True):
        ax.plot(t0 + SAMPLE_PERIOD_S * np.arange(u.size), u, lw=0.5, color="tab:blue",
                alpha=0.6)
    t_cmd = _seconds(command["log_time_ns"], origin)
    if starts.size:
        horizon = max((u.size for u in rows), default=1) * SAMPLE_PERIOD_S
        shown = (t_cmd >= starts[0]) & (t_cmd <= starts[-1] + horizon)
        ax.plot(t_cmd[shown], command["command_mA"][shown], color="k", lw=2.0,
                label="applied u(k)")
        ax.plot([], [], lw=0.5, color="tab:blue", label="predicted û(k+i|k), i < H_u")
        ax.legend(loc="best", fontsize=8)
    ax.set_ylabel("current [mA]")
    ax.set_title(f"MPC prediction waterfall ({len(rows)} recorded ticks)", fontsize=9)


def axis_names(data: SessionData) -> list[str]:
    """The axes of a session recorded with ``--axes`` (their ``/axis/NAME/command``), in
    order; none for a single-axis session."""
    return [name.split("/")[2] for name in sorted(data.topic_counts)
            if name.startswith("/axis/") and name.endswith("/command")]


def plot_axes(data: SessionData, names: list[str], out_png: str) -> None:
    """Several axes: each axis' tracking error and current over time, and for a path the
    measured X-Y points against the path and the contour error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    contour = data.arrays("/path/contour")
    has_path = contour["log_time_ns"].size > 0
    fig, axes = plt.subplots(2 + has_path, 1, figsize=(10, 2.8 * (2 + has_path)),
                             squeeze=False)
    axes = axes[:, 0]
    info = kpis(data)
    fig.suptitle(f"servo session on {len(names)} axes: {info.get('controller', '?')}, "
                 f"{info.get('reference', '')}", fontsize=10)
    origin: int | None = None
    for name in names:
        command = data.arrays(f"/axis/{name}/command")
        if command["log_time_ns"].size == 0:
            continue
        origin = int(command["log_time_ns"][0]) if origin is None else origin
        t = _seconds(command["log_time_ns"], origin)
        axes[0].plot(t, command["error_deg"], lw=0.8, label=f"axis {name}")
        axes[1].plot(t, command["command_mA"], lw=0.8, label=f"axis {name}")
    axes[0].set_ylabel("error [deg]")
    axes[0].set_title("tracking error per axis (position - reference)", fontsize=9)
    axes[1].set_ylabel("current [mA]")
    axes[1].set_title("commanded current per axis", fontsize=9)
    for ax in axes[:2]:
        ax.legend(loc="best", fontsize=8)
    axes[1].set_xlabel("time [s]")
    if has_path:
        ax = axes[2]
        radius = float(info.get("contour", {}).get("radius_deg") or 0.0)
        x, y = contour["x_deg"], contour["y_deg"]
        if radius:
            angle = np.linspace(0.0, 2.0 * np.pi, 361)
            ax.plot(radius * (np.cos(angle) - 1.0), radius * np.sin(angle), "k--", lw=0.8,
                    label="path")
        ax.plot(x, y, lw=0.9, label=f"measured ({names[0]}, {names[1]})")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"axis {names[0]} [deg]")
        ax.set_ylabel(f"axis {names[1]} [deg]")
        error = contour["contour_error_deg"]
        ax.set_title(f"X-Y: contour error max {np.abs(error).max():.4f} deg", fontsize=9)
        ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(out_png, dpi=110)
    plt.close(fig)


def plot_motion(data: SessionData, out_png: str) -> None:
    """A move's or a homing's profile as the drive ran it (``hil drive move|home``):
    position (and a move's target), velocity and current over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    feedback = data.arrays("/drive/feedback")
    sent = data.arrays("/drive/motion")
    stamps = feedback["log_time_ns"]
    fig, axes = plt.subplots(3, 1, figsize=(10, 7.8), sharex=True)
    info = kpis(data)
    fig.suptitle(f"drive {info.get('motion', 'motion')}: {info.get('drive', '')}", fontsize=10)
    if stamps.size == 0:
        axes[0].text(0.5, 0.5, "no /drive/feedback messages recorded", ha="center")
    else:
        t = _seconds(stamps, int(stamps[0]))
        axes[0].plot(t, feedback["position_deg"], lw=1.0, label="position")
        if "target_deg" in sent and sent["log_time_ns"].size:
            axes[0].plot(_seconds(sent["log_time_ns"], int(stamps[0])), sent["target_deg"],
                         "k--", lw=0.8, label="target")
        axes[1].plot(t, feedback["velocity_deg_s"], lw=0.9)
        axes[2].plot(t, feedback["current_mA"], lw=0.9)
    for ax, label in zip(axes, ("angle [deg]", "velocity [deg/s]", "current [mA]"),
                         strict=True):
        ax.set_ylabel(label)
    axes[0].legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
