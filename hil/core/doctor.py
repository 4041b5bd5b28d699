"""``hil doctor``: qualify this machine for real-time runs, in the spirit of LinuxCNC's
latency-test and cyclictest.

The bare fixed-rate loop (no device, no recording) runs at 1 kHz and 2 kHz under the same
hardening a ``--realtime`` session gets; its lateness (wake-up minus deadline) and the share of
ticks it had to skip are what any real-time session on this machine can hope for at best.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from hil.core.clock import RealtimeClock
from hil.core.loop import FixedRateLoop, FunctionTask
from hil.core.realtime import Hardening, advice, machine_report

RATES_HZ = (1000, 2000)


def measure_loop(rate_hz: int, duration_s: float) -> dict[str, float]:
    """Lateness p50/p99/max [us] and skipped ticks [%] of the bare loop at ``rate_hz``."""
    loop = FixedRateLoop(RealtimeClock(), 1.0 / rate_hz, [FunctionTask("tick", 1)],
                         handle_signals=False)
    loop.run(duration_s=duration_s)
    stats = loop.stats["tick"]
    scheduled = stats.runs + stats.missed
    lateness = stats.lateness
    return {"p50_us": lateness.percentile(50), "p99_us": lateness.percentile(99),
            "max_us": round(lateness.max_us, 1), "missed_pct":
            round(100.0 * stats.missed / scheduled, 4) if scheduled else 0.0,
            "ticks": scheduled}


def run_doctor(duration_s: float, rates_hz: Sequence[int] = RATES_HZ,
               progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The machine report, the hardening steps and the bare loop at each rate."""
    hardening = Hardening()
    steps = hardening.apply()
    try:
        loops = {}
        for rate in rates_hz:
            if progress is not None:
                progress(f"bare loop at {rate} Hz for {duration_s:g} s ...")
            loops[str(rate)] = measure_loop(rate, duration_s)
    finally:
        hardening.restore()
    report = machine_report()
    return {"loops": loops, "os": report,
            "hardening": {s.name: {"granted": s.granted, "detail": s.detail} for s in steps},
            "advice": advice(report, steps)}


def format_doctor(result: dict[str, Any]) -> str:
    """The report as aligned text."""
    lines = [f"{'loop':<10} {'p50 us':>8} {'p99 us':>8} {'max us':>9} {'skipped %':>10}"]
    for rate, row in result["loops"].items():
        lines.append(f"{rate + ' Hz':<10} {row['p50_us']:>8.1f} {row['p99_us']:>8.1f} "
                     f"{row['max_us']:>9.1f} {row['missed_pct']:>10.3f}")
    lines.append("")
    lines.append("hardening (as under --realtime):")
    for name, step in result["hardening"].items():
        lines.append(f"  {name:<13} {'granted' if step['granted'] else 'REFUSED'}: "
                     f"{step['detail']}")
    lines.append("")
    lines.append("machine:")
    for key, value in result["os"].items():
        lines.append(f"  {key:<24} {value}")
    if result["advice"]:
        lines.append("")
        lines.append("to do better:")
        lines += [f"  - {line}" for line in result["advice"]]
    return "\n".join(lines)
