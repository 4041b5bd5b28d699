"""The bench session's panels in the HTML report (entry point ``hil.html_panels``), as the
PNG of ``hil report --out`` draws them: the total apparent power with the machining profile
and the contracted limit, the relay states, and the resource levels with their bounds."""

from __future__ import annotations

import numpy as np

from hil.bench.report import machining_profile, session_config
from hil.core.html_report.panels import Panel, Trace
from hil.core.recording.reader import SessionData


def bench_panels(data: SessionData, origin_ns: int) -> list[Panel]:
    """Power, relays and levels over session time (a panel only where the session has it)."""
    config = session_config(data)
    bench = config.get("bench", {})
    power, relays, levels = (data.arrays(topic)
                             for topic in ("/bench/power", "/bench/relays", "/bench/levels"))
    names = [k for k in relays if k not in ("log_time_ns", "link_up")
             and not k.endswith("_commanded")]
    t_relays = (relays["log_time_ns"] - origin_ns) / 1e9
    panels = []
    if "total_va" in power:
        traces = [Trace("total S (measured)", (power["log_time_ns"] - origin_ns) / 1e9,
                        np.asarray(power["total_va"], float))]
        profile = machining_profile({k: relays[k].astype(float) for k in names}, bench)
        if profile is not None:
            traces.append(Trace("machining profile (nominal)", t_relays, profile, step=True))
        limit = config.get("controllers", {}).get("eec", {}).get("limit_va")
        lines = ((float(limit), f"contracted {limit:g} VA"),) if limit else ()
        panels.append(Panel("total apparent power", "S [VA]", tuple(traces), lines))
    if names:
        panels.append(Panel(
            "relays (on = raised)", "relay",
            tuple(Trace(name, t_relays, relays[name] * 0.8 + k, step=True)
                  for k, name in enumerate(names)),
            ticks=tuple((k + 0.4, name) for k, name in enumerate(names))))
    resources = bench.get("plant", {}).get("resources", {})
    level_names = [k for k in levels if k != "log_time_ns"]
    if level_names:
        t = (levels["log_time_ns"] - origin_ns) / 1e9
        bounds = tuple((float(b), f"{name} bound {b:g}") for name in level_names
                       for b in resources.get(name, {}).get("bounds", []) or [])
        panels.append(Panel("resource levels q_j (dotted: bounds)", "level",
                            tuple(Trace(name, t, np.asarray(levels[name], float))
                                  for name in level_names), bounds))
    return panels
