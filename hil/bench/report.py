"""The bench session's part of ``hil report``.

* the plot (``--out F.png``), four panels: the total apparent power with the machining profile
  (base load plus the rated power of the machining loads that are on, when the config
  describes them) and the contracted limit; the relay states; the resource levels with their
  bounds; the KPI table;
* the distribution of the EEC's solve times (from every ``/eec/plan`` message, so truncated
  sessions too): percentiles, a histogram, the solve statuses and the largest gap; JSON key
  ``solve_times``.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from typing import Any

import numpy as np

from hil.core.recording.reader import SessionData
from hil.core.report import KPI_ROW_IN, kpi_table, kpi_table_rows

SOLVE_EDGES_MS = (0.0, 5.0, 10.0, 20.0, 50.0, 100.0, 250.0, 500.0, 1000.0)


class SolveTimes:
    """The ``solve_times`` section of ``hil report`` (entry point ``hil.summaries``)."""

    key = "solve_times"

    def section(self, data: SessionData) -> dict[str, Any]:
        """Percentiles (ms), histogram, statuses and the largest gap of the recorded plans
        (empty without any)."""
        plans = [m for _, m in data.topic("/eec/plan")
                 if isinstance(m, dict) and isinstance(m.get("solve_ms"), (int, float))]
        if not plans:
            return {}
        ms = np.array([float(m["solve_ms"]) for m in plans])
        counts = np.bincount(np.searchsorted(SOLVE_EDGES_MS, ms, side="right") - 1,
                             minlength=len(SOLVE_EDGES_MS))
        tops = [*SOLVE_EDGES_MS[1:], None]
        gaps = [float(m["gap"]) for m in plans
                if isinstance(m.get("gap"), (int, float)) and math.isfinite(m["gap"])]
        return {
            "count": int(ms.size),
            "ms": {"min": round(float(ms.min()), 3), "p50": round(float(np.median(ms)), 3),
                   "p90": round(float(np.percentile(ms, 90)), 3),
                   "p99": round(float(np.percentile(ms, 99)), 3),
                   "max": round(float(ms.max()), 3), "mean": round(float(ms.mean()), 3)},
            "histogram": [{"from_ms": lo, "to_ms": hi, "count": int(n)}
                          for lo, hi, n in zip(SOLVE_EDGES_MS, tops, counts, strict=True)],
            "status": dict(sorted(Counter(str(m.get("status", "")) for m in plans).items())),
            "max_gap": max(gaps, default=0.0),
        }

    def lines(self, section: dict[str, Any]) -> list[str]:
        """The section as text: a percentile line, a bar per histogram bin, the statuses."""
        ms = section["ms"]
        out = [f"solve times ({section['count']} plans, /eec/plan)   p50 {ms['p50']:.1f}  "
               f"p90 {ms['p90']:.1f}  p99 {ms['p99']:.1f}  max {ms['max']:.1f} ms"]
        most = max(b["count"] for b in section["histogram"]) or 1
        for b in section["histogram"]:
            label = (f"{b['from_ms']:g}-{b['to_ms']:g} ms" if b["to_ms"] is not None
                     else f">= {b['from_ms']:g} ms")
            bar = "#" * math.ceil(40 * b["count"] / most)
            out.append(f"  {label:<14} {b['count']:>6}  {bar}")
        statuses = ", ".join(f"{n} {s}" for s, n in section["status"].items())
        out.append(f"  status: {statuses}; largest gap {section['max_gap']:.3g}")
        return out


SOLVE_TIMES = SolveTimes()


def session_config(data: SessionData) -> dict[str, Any]:
    """The run's configuration as recorded in the session (empty when unreadable)."""
    raw = data.metadata.get("config", {}).get("json")
    try:
        return json.loads(raw) if raw else {}
    except ValueError:
        return {}


def machining_profile(relays: dict[str, np.ndarray], bench: dict[str, Any]) -> np.ndarray | None:
    """Nominal machining power: base load + rated VA of every machining load that is on."""
    plant = bench.get("plant", {})
    loads = plant.get("loads", {})
    machining = {name for stage in bench.get("sequence", {}).get("stages", [])
                 for name in stage.get("on", [])}
    if "base" not in plant or not machining or not relays:
        return None
    n = len(next(iter(relays.values())))
    profile = np.full(n, float(plant["base"].get("va", 0.0)))
    for load in loads.values():
        relay = load.get("relay")
        if relay in machining and relay in relays:
            profile += float(load.get("va", 0.0)) * relays[relay]
    return profile


def _seconds(stamps: np.ndarray, t0: int) -> np.ndarray:
    return (stamps - t0) / 1e9


def plot_bench(data: SessionData, out_png: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    config = session_config(data)
    bench = config.get("bench", {})
    power = data.arrays("/bench/power")
    relays = data.arrays("/bench/relays")
    levels = data.arrays("/bench/levels")
    stamps = [a["log_time_ns"] for a in (power, relays, levels) if a["log_time_ns"].size]
    t0 = int(min(s[0] for s in stamps)) if stamps else 0
    rows = kpi_table_rows(data)
    table_height = KPI_ROW_IN * (len(rows) + 1)
    fig, axes = plt.subplots(4, 1, figsize=(12, 8.5 + table_height),
                             gridspec_kw={"height_ratios": [3, 1.4, 2, table_height]})
    axes[1].sharex(axes[0])
    axes[2].sharex(axes[0])
    ax = axes[0]
    if "total_va" in power:
        t = _seconds(power["log_time_ns"], t0)
        ax.plot(t, power["total_va"], lw=0.6, color="tab:blue", label="total S (measured)")
        relay_states = {k: relays[k].astype(float) for k in relays
                        if k != "log_time_ns" and not k.endswith("_commanded")
                        and k != "link_up"}
        profile = machining_profile(relay_states, bench)
        if profile is not None:
            ax.step(_seconds(relays["log_time_ns"], t0), profile, where="post", lw=0.9,
                    color="tab:gray", label="machining profile (nominal)")
    limit = config.get("controllers", {}).get("eec", {}).get("limit_va")
    if limit:
        ax.axhline(limit, color="tab:red", lw=0.8, ls="--", label=f"contracted {limit:g} VA")
    ax.set_ylabel("VA")
    ax.set_title(f"{data.path}: total apparent power")
    ax.legend(loc="upper right", fontsize=8)
    ax = axes[1]
    names = [k for k in relays if k not in ("log_time_ns", "link_up")
             and not k.endswith("_commanded")]
    if names:
        t = _seconds(relays["log_time_ns"], t0)
        for k, name in enumerate(names):
            ax.step(t, relays[name] * 0.8 + k, where="post", lw=0.9, label=name)
        ax.set_yticks(np.arange(len(names)) + 0.4, names)
    ax.set_title("relays (on = raised)")
    ax = axes[2]
    resources = bench.get("plant", {}).get("resources", {})
    if levels["log_time_ns"].size:
        t = _seconds(levels["log_time_ns"], t0)
        for name in [k for k in levels if k != "log_time_ns"]:
            line = ax.plot(t, levels[name], lw=0.9, label=name)[0]
            bounds = resources.get(name, {}).get("bounds")
            if bounds:
                for b in bounds:
                    ax.axhline(b, color=line.get_color(), lw=0.6, ls=":")
    ax.set_ylabel("level")
    ax.set_xlabel("time [s]")
    ax.set_title("resource levels q_j (dotted: bounds)")
    ax.legend(loc="upper right", fontsize=8)
    kpi_table(axes[3], rows)
    fig.tight_layout(h_pad=1.0)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
