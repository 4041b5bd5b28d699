"""``hil doctor``: qualify this machine for real-time runs, in the spirit of LinuxCNC's
latency-test and cyclictest.

The bare fixed-rate loop (no device, no recording) runs at 1 kHz and 2 kHz under the same
hardening a ``--realtime`` session gets; its lateness (wake-up minus deadline) and the share of
ticks it had to skip are what any real-time session on this machine can hope for at best.
It also reports what a drive emulator standing in for hardware would be granted (the helper
hardening of ``hil emulate drive --harden``, which a ``--realtime`` run against ``emulated``
asks for), tried on a thread of its own.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any

from hil.core.clock import RealtimeClock
from hil.core.loop import FixedRateLoop, FunctionTask
from hil.core.realtime import Hardening, Step, advice, machine_report

RATES_HZ = (1000, 2000)
#: what a 2 kHz servo session needs of the bare loop (its period is 500 us): no tick skipped,
#: lateness p99 within a fifth of the period (the tick's own work, read-compute-write, takes
#: ~100 us at p99 with the MPC) and never a whole period late
SERVO_RATE_HZ = 2000
MAX_P99_US = 100.0
MAX_LATE_US = 500.0


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
            "emulator_hardening": {s.name: {"granted": s.granted, "detail": s.detail}
                                   for s in helper_steps()},
            "advice": advice(report, steps), "verdict": verdict(loops)}


def helper_steps() -> list[Step]:
    """What a drive emulator's serving thread would be granted
    (:meth:`Hardening.for_answering_helper`), tried on a thread started for it and undone."""
    steps: list[Step] = []

    def attempt() -> None:
        helper = Hardening.for_answering_helper()
        steps.extend(helper.apply())
        helper.restore()

    thread = threading.Thread(target=attempt, name="doctor-helper")
    thread.start()
    thread.join()
    return steps


def verdict(loops: dict[str, dict[str, float]]) -> dict[str, Any]:
    """Whether this machine is fit for the 2 kHz servo loop in real time, and why (the bare
    loop against :data:`MAX_P99_US`, :data:`MAX_LATE_US` and no skipped tick)."""
    row = loops.get(str(SERVO_RATE_HZ))
    if row is None:
        return {"fit_for_2khz": None, "because": f"the {SERVO_RATE_HZ} Hz loop was not run"}
    problems = []
    if row["missed_pct"] > 0:
        problems.append(f"{row['missed_pct']:g} % of the ticks were skipped")
    if row["p99_us"] > MAX_P99_US:
        problems.append(f"lateness p99 {row['p99_us']:.0f} us > {MAX_P99_US:.0f} us")
    if row["max_us"] > MAX_LATE_US:
        problems.append(f"lateness max {row['max_us']:.0f} us > {MAX_LATE_US:.0f} us "
                        "(a whole period)")
    if problems:
        return {"fit_for_2khz": False, "because": "; ".join(problems)}
    return {"fit_for_2khz": True,
            "because": f"lateness p99 {row['p99_us']:.0f} us <= {MAX_P99_US:.0f} us, max "
                       f"{row['max_us']:.0f} us <= {MAX_LATE_US:.0f} us, no tick skipped"}


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
    lines.append("hardening of a drive emulator (hil emulate drive --harden, as --realtime "
                 "starts it):")
    for name, step in result["emulator_hardening"].items():
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
    fit = result["verdict"]["fit_for_2khz"]
    lines.append("")
    lines.append(f"fit for the 2 kHz servo loop in real time: "
                 f"{'yes' if fit else 'no' if fit is False else 'unknown'}, because "
                 f"{result['verdict']['because']}")
    return "\n".join(lines)
