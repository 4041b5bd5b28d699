"""The servo half of ``hil demo``: MPC (FOH) vs PID on a 2 deg sine through the emulated CAN drive.

Two cases (DESIGN.md): 1 Hz at the paper's 1000 mA limit, and 10 Hz at the motor's rated 12 A
(2 deg at 10 Hz needs about 2.8 A, so at 1000 mA every controller saturates and the paper's
absolute figures cannot be reproduced from its printed model; see ``hil servo figures``). MPC:
FOH ERT, H_t = H_u = 8, H_p = 50, Q = 1e6, R = 1; PID: Table I with the notch on the
resonance. Each run is a lockstep session through the CiA 402 link, recorded to MCAP and drawn
to PNG; the KPIs are taken over one reference cycle after ``SETTLE_S`` (the start-up transient,
as in the Figs. 7-8 table), so the cumulative error is the paper's per-cycle metric.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from hil.core.reader import read_session
from hil.core.recorder import RecordingOptions
from hil.core.report import plot_session
from hil.servo.run import ServoRunConfig, run_servo

SETTLE_S = 0.5
CASES = ((1.0, 1000.0), (10.0, 12000.0))  # (sine frequency [Hz], current limit [mA])
CONTROLLERS = ("mpc", "pid")
AMPLITUDE_DEG = 2.0


def run_servo_demo(out_dir: str | Path, echo: Callable[[str], None] | None = print,
                   recording: RecordingOptions | None = None) -> list[dict[str, Any]]:
    """Run the four sessions into ``out_dir`` (MCAP + PNG each); return one row per run and,
    unless ``echo`` is None, print the comparison table with it."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for frequency, limit in CASES:
        for controller in CONTROLLERS:
            name = f"servo-{controller}-{frequency:g}hz-{limit / 1000:g}a"
            mcap = str(out / f"{name}.mcap")
            config = ServoRunConfig(
                controller=controller, ert="foh", ht=8, hu=8, hp=50, umax=limit,
                reference=f"sine:amplitude={AMPLITUDE_DEG:g},frequency={frequency:g}",
                duration_s=SETTLE_S + 1.0 / frequency, settle_s=SETTLE_S,
                out=mcap, recording=recording or RecordingOptions())
            kpis = run_servo(config).kpis
            png = out / f"{name}.png"
            plot_session(read_session(mcap), str(png))
            rows.append({"frequency_hz": frequency, "umax_mA": limit, **kpis, "png": str(png)})
    if echo is not None:
        echo(format_servo_demo(rows))
    return rows


def format_servo_demo(rows: list[dict[str, Any]]) -> str:
    """The comparison table of :func:`run_servo_demo`."""
    lines = [
        f"servo: MPC (FOH, H_t = H_u = 8, H_p = 50) vs cascaded PID, {AMPLITUDE_DEG:g} deg sine "
        "through the emulated CAN drive (lockstep)",
        f"KPIs over one cycle after {SETTLE_S:g} s; error = position - reference",
        f"{'case':<16}{'ctrl':<6}{'max err deg':>12}{'max err %':>10}{'rms deg':>9}"
        f"{'cum. deg':>10}{'peak mA':>9}{'step p99 us':>12}{'x real time':>12}",
    ]
    for row in rows:
        case = f"{row['frequency_hz']:g} Hz, {row['umax_mA']:g} mA"
        lines.append(
            f"{case:<16}{row['controller']:<6}{row['max_error_deg']:>12.4f}"
            f"{row['max_error_pct']:>10.1f}{row['rms_error_deg']:>9.4f}"
            f"{row['cumulative_error_deg']:>10.2f}{row['peak_current_mA']:>9.0f}"
            f"{row['step_us']['p99']:>12.1f}{row['realtime_factor']:>12.1f}")
    lines.append("sessions: " + ", ".join(Path(r["mcap"]).name for r in rows) + " (+ .png)")
    return "\n".join(lines)
