"""The picture of a sweep (``sweep.png``): for the bench, energy J1 against peak J2 with the
Pareto front marked; for the servo, each tracking KPI against each swept key."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from hil.sweep.results import finite
from hil.sweep.space import format_value

SERVO_KPIS = ("max_error_deg", "rms_error_deg", "cumulative_error_deg", "peak_current_mA")


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats on both coordinates (both minimised),
    sorted by the first coordinate."""
    front = [i for i, (x, y) in enumerate(points)
             if not any(x2 <= x and y2 <= y and (x2 < x or y2 < y) for x2, y2 in points)]
    return sorted(front, key=lambda i: points[i])


def plot_sweep(kind: str, rows: Sequence[Mapping[str, Any]], keys: Sequence[str],
               out_png: str) -> bool:
    """Draw the sweep to ``out_png``; False when no trial has KPIs to draw."""
    done = [r for r in rows if r.get("kpis")]
    if not done:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = _bench(plt, done) if kind == "bench" else _servo(plt, done, keys)
    fig.tight_layout()
    fig.savefig(out_png, dpi=100)
    plt.close(fig)
    return True


def _bench(plt: Any, rows: Sequence[Mapping[str, Any]]) -> Any:
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    points = [(float(r["kpis"]["J1_VA"]), float(r["kpis"]["J2_VA"])) for r in rows]
    ax.scatter([p[0] for p in points], [p[1] for p in points], color="tab:blue", label="trials")
    front = pareto_front(points)
    ax.plot([points[i][0] for i in front], [points[i][1] for i in front], "o-",
            color="tab:red", label="Pareto front")
    for i in front:
        ax.annotate(rows[i]["name"], points[i], fontsize=7, xytext=(4, 4),
                    textcoords="offset points")
    ax.set_xlabel("energy J1 [VA·s]")
    ax.set_ylabel("peak J2 [VA]")
    ax.set_title(f"bench sweep: {len(rows)} trials")
    ax.grid(True, alpha=0.3)
    ax.legend()
    return fig


def _servo(plt: Any, rows: Sequence[Mapping[str, Any]], keys: Sequence[str]) -> Any:
    keys = list(keys) or ["trial"]
    fig, axes = plt.subplots(len(SERVO_KPIS), len(keys), squeeze=False,
                             figsize=(3.6 * len(keys), 2.4 * len(SERVO_KPIS)))
    for col, key in enumerate(keys):
        values = [r["params"].get(key, r["name"]) if key != "trial" else r["name"]
                  for r in rows]
        numeric = all(finite(v) is not None for v in values)
        labels = sorted({format_value(v) for v in values}) if not numeric else []
        xs = [float(v) if numeric else labels.index(format_value(v)) for v in values]
        for row_index, kpi in enumerate(SERVO_KPIS):
            ax = axes[row_index][col]
            ys = [finite(r["kpis"].get(kpi)) for r in rows]
            ax.scatter([x for x, y in zip(xs, ys, strict=True) if y is not None],
                       [y for y in ys if y is not None], s=14)
            if not numeric:
                ax.set_xticks(range(len(labels)), labels, rotation=30, fontsize=7)
            ax.set_ylabel(kpi, fontsize=8)
            ax.grid(True, alpha=0.3)
        axes[-1][col].set_xlabel(key)
    fig.suptitle(f"servo sweep: {len(rows)} trials")
    return fig
