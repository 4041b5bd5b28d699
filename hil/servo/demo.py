"""The servo half of ``hil demo``: MPC (FOH) vs PID on a 2 deg sine through the emulated CAN drive.

Two cases (the servo paper's Figs. 7-8): 1 Hz at the paper's 1000 mA limit, and 10 Hz at the
motor's rated 12 A
(2 deg at 10 Hz needs about 2.8 A, so at 1000 mA every controller saturates and the paper's
absolute figures cannot be reproduced from its printed model; see ``hil servo figures``). MPC:
FOH ERT, H_t = H_u = 8, H_p = 50, Q = 1e6, R = 1; PID: Table I with the notch on the
resonance. Each run is a lockstep session through the CiA 402 link, recorded to MCAP and drawn
to PNG; the KPIs are taken over one reference cycle after ``SETTLE_S`` (the start-up transient,
as in the Figs. 7-8 table), so the cumulative error is the paper's per-cycle metric.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

from hil.controllers.base import ServoController
from hil.controllers.servo.mpc import MpcConfig, TrajectoryMpc
from hil.controllers.servo.pid import CascadedPid, PidConfig
from hil.controllers.servo.references import Reference
from hil.controllers.servo.sim import PAPER_CASES, cycle_error
from hil.core.recording.reader import read_session
from hil.core.recording.recorder import RecordingOptions
from hil.core.report import plot_session
from hil.errors import HilError
from hil.servo.config import drive_for
from hil.servo.run import ServoRunOptions, run_servo
from hil.sweep.engine import Engine
from hil.sweep.space import Trial, named

SETTLE_S = 0.5
CASES = ((1.0, 1000.0), (10.0, 12000.0))  # (sine frequency [Hz], current limit [mA])
CONTROLLERS = ("mpc", "pid")
AMPLITUDE_DEG = 2.0


def run_servo_demo(out_dir: str | Path, echo: Callable[[str], None] | None = print,
                   recording: RecordingOptions | None = None, quiet: bool = False
                   ) -> list[dict[str, Any]]:
    """Run the four sessions into ``out_dir`` (MCAP + PNG each, ``quiet``: without their
    progress lines); return one row per run and, unless ``echo`` is None, print the comparison
    table with it."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for frequency, limit in CASES:
        for controller in CONTROLLERS:
            name = f"servo-{controller}-{frequency:g}hz-{limit / 1000:g}a"
            mcap = str(out / f"{name}.mcap")
            config = ServoRunOptions(
                controller=controller, ert="foh", ht=8, hu=8, hp=50,
                drive_overrides=drive_for(limit),
                reference=f"sine:amplitude={AMPLITUDE_DEG:g},frequency={frequency:g}",
                duration_s=SETTLE_S + 1.0 / frequency, settle_s=SETTLE_S,
                out=mcap, recording=recording or RecordingOptions(), quiet=quiet)
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


# -- hil servo figures: the Figs. 7-8 table as a preset sweep ----------------------------------


def figure_trials(horizons: Sequence[int], hp: int, q: float, r: float, amplitude: float,
                  cases: Iterable[tuple[float, float]] = PAPER_CASES) -> list[Trial]:
    """The points of the Figs. 7-8 table: per case, MPC ZOH at every H_t (H_t = 1 is the
    set-point MPC the table is normalised to), MPC FOH from H_t = 2, PID with and without
    velocity feed-forward."""
    points = []
    for frequency, limit in cases:
        case = {"frequency_hz": frequency, "current_limit_mA": limit, "hp": hp, "q": q,
                "r": r, "amplitude_deg": amplitude}
        points += [{**case, "controller": "mpc", "ert": "zoh", "ht": ht} for ht in horizons]
        points += [{**case, "controller": "mpc", "ert": "foh", "ht": ht}
                   for ht in horizons if ht >= 2]
        points += [{**case, "controller": "pid", "vff": vff} for vff in (False, True)]
    return named(points)


def run_figure_trial(trial: Trial) -> dict[str, Any]:
    """One point of the table, simulated offline: its cycle metrics as the row's KPIs."""
    p = trial.params
    limit = p["current_limit_mA"]
    make: Callable[[Reference], ServoController]
    if p["controller"] == "mpc":
        mpc = MpcConfig(ht=p["ht"], hu=p["ht"], hp=p["hp"], ert=p["ert"], q=p["q"], r=p["r"],
                        u_min=-limit, u_max=limit)
        make = partial(TrajectoryMpc, config=mpc)
    else:
        make = partial(CascadedPid, config=PidConfig(u_max=limit, velocity_feedforward=p["vff"]))
    kpis = cycle_error(make, p["frequency_hz"], p["amplitude_deg"], limit)
    return {"name": trial.name, "params": p, "status": "ok", "kpis": kpis}


def figure_table_of(rows: Sequence[Mapping[str, Any]],
                    horizons: Sequence[int]) -> list[dict[str, Any]]:
    """The rows of :func:`figure_trials` as the table of
    :func:`hil.controllers.servo.sim.figure_table` (same keys, same numbers)."""
    cases: dict[tuple[float, float], dict[tuple[Any, ...], Any]] = {}
    for row in rows:
        p = row["params"]
        entry = cases.setdefault((p["frequency_hz"], p["current_limit_mA"]), {})
        key = (p["controller"], p.get("ert", p.get("vff")), p.get("ht"))
        entry[key] = row["kpis"]
    table = []
    for (frequency, limit), entry in cases.items():
        setpoint = entry[("mpc", "zoh", 1)] if 1 in horizons else None
        zoh = [entry[("mpc", "zoh", ht)] for ht in horizons]
        foh = [entry[("mpc", "foh", ht)] if ht >= 2 else None for ht in horizons]
        pid_plain, pid_vff = entry[("pid", False, None)], entry[("pid", True, None)]
        base = setpoint["cumulative_error_deg"] if setpoint else None

        def normalised(metrics: Mapping[str, float] | None, base: float | None = base
                       ) -> float | None:
            return None if metrics is None or base is None else (
                metrics["cumulative_error_deg"] / base)

        table.append({
            "frequency_hz": frequency, "current_limit_mA": limit, "horizons": list(horizons),
            "setpoint": setpoint, "pid": normalised(pid_plain), "pid_vff": normalised(pid_vff),
            "zoh": [normalised(m) for m in zoh], "foh": [normalised(m) for m in foh],
            "absolute": {"pid": pid_plain, "pid_vff": pid_vff, "zoh": zoh, "foh": foh},
        })
    return table


def run_figures_sweep(horizons: Sequence[int], hp: int, q: float, r: float, amplitude: float,
                      engine: Engine) -> list[dict[str, Any]]:
    """``hil servo figures``: the table's points as a sweep on ``engine`` (one after another
    in this process, or Ray tasks); the table. A failed point is an error."""
    trials = figure_trials(horizons, hp, q, r, amplitude)
    rows: dict[str, dict[str, Any]] = {}
    engine.run(run_figure_trial, trials, lambda row: rows.__setitem__(row["name"], row))
    failed = [row for row in rows.values() if row["status"] != "ok"]
    if failed:
        raise HilError(f"figures: point {failed[0]['name']} failed: {failed[0].get('error')}")
    return figure_table_of([rows[t.name] for t in trials], horizons)
