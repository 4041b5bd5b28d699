"""``hil paper servo``: the servo paper (Stephens, Manzie, Good, IEEE TII 2013) reproduced
from hil's lockstep sessions on the emulated drive, every result beside the paper's.

What runs (the conditions: ``hil/configs/paper_servo.toml``, :mod:`hil.paper.servo_conditions`):

* Figs. 5-8: MPC with ZOH- and FOH-ERT at every H_t = H_u of the conditions and the cascaded
  PID + notch (Table I) on the 2 deg sines, 1 Hz and 10 Hz at the paper's ±1000 mA and 10 Hz
  again at the motor's rated 12 A; max, RMS and cumulative error over one cycle;
* Figs. 9-10: the predicted inputs of ZOH and FOH at H_t = H_u = 4 against the applied ones;
* section III-C: the explicit MPC's regions, controllers, tree nodes and depth, and the
  evaluation time of its law against the online QP's (:mod:`hil.paper.servo_empc`);
* Figs. 14-16: the explicit MPC and the PID on the 270 deg, 60 rpm trapezoid, the explicit
  MPC against a position disturbance, with the controller of every tick;
* the sweeps that explain each difference by measurement (:func:`explain`).

Every session is a ``hil servo run`` in lockstep (:mod:`hil.paper.servo_runs`), kept in the
report's sessions folder. :func:`measure` returns the results as one JSON-able dict;
:func:`reproduce` adds the figures and tables of the report (:mod:`hil.paper.servo_report`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from hil.paper.servo_claims import claims
from hil.paper.servo_conditions import ServoConditions, SineCase, load_conditions
from hil.paper.servo_explain import PAPER_FIG5, PAPER_FIG6, explain
from hil.paper.servo_friction import friction_sweep
from hil.paper.servo_measures import (
    controllers_used,
    prediction_match,
    push_response,
    share_in,
    tracking,
)
from hil.paper.servo_plan import matched_pid, plan
from hil.paper.servo_runs import Session, SessionRunner

if TYPE_CHECKING:
    from hil.paper.report import PaperOptions, PaperReport


def reproduce(options: PaperOptions) -> PaperReport:
    """The paper reproduced under its conditions (``--quick``: the shorter ones): the
    sessions, the figures and the report."""
    from hil.paper.servo_report import report_of

    started = time.perf_counter()
    conditions = load_conditions(options.quick)
    report = report_of(measure(conditions, options), conditions, options)
    report.wall_s = time.perf_counter() - started
    return report


def measure(c: ServoConditions, options: PaperOptions) -> dict[str, Any]:
    """Run every experiment (sessions into ``options.sessions``); the results."""
    started = time.perf_counter()
    options.sessions.mkdir(parents=True, exist_ok=True)
    echo = options.progress

    from hil.paper import servo_empc

    laws = servo_empc.build_laws(c, echo)
    law = laws[c.empc_ht]
    runs = plan(c, law)
    run = SessionRunner(options.sessions, c, planned=len({r.name for r in runs.values()}),
                        echo=echo)
    done = {key: run(spec) for key, spec in runs.items()}
    done.update(matched_pid(c, done, run))
    results: dict[str, Any] = {
        "paper": "servo", "quick": c.quick, "conditions": conditions_of(c),
        "sine": sine_tables(c, done),
        "waterfall": waterfall(c, done),
        "empc": explicit_mpc(c, laws, done, echo),
        "trapezoid": trapezoid(c, done),
        "disturbance": disturbance(c, done),
    }
    results["fig5"], results["fig6"] = fig5_and_6(c, done)
    results["explain"] = explain(c, done, results["empc"]["box_sweep"])
    echo("Figs. 9-10 with viscous friction (offline)")
    results["explain"]["friction"] = friction_sweep(c)
    results["claims"] = claims(c, results)
    results["sessions"] = {key: s.mcap for key, s in done.items()}
    results["session_wall_s"] = round(run.wall_s, 1)
    results["measure_s"] = round(time.perf_counter() - started, 1)
    return results


# -- the tables ----------------------------------------------------------------------------


def sine_tables(c: ServoConditions, done: dict[str, Session]) -> list[dict[str, Any]]:
    """Figs. 7-8, one panel per sine case: every MPC variant and the PID, their KPIs and the
    cumulative error normalised to set-point MPC (ZOH, H_t = 1)."""
    panels = []
    for case in c.sine_cases:
        base = done[f"{case.name}/zoh/1"]["cumulative_error_deg"]
        rows = []
        for ert in ("zoh", "foh"):
            for ht in c.horizons:
                key = f"{case.name}/{ert}/{ht}"
                if key in done:
                    row = tracking(done[key])
                    rows.append({"ert": ert, "ht": ht, **row,
                                 "normalised": row["cumulative_error_deg"] / base})
        pid = tracking(done[f"{case.name}/pid"])
        pid["normalised"] = pid["cumulative_error_deg"] / base
        figure = "Fig. 7" if case.frequency_hz == min(c.frequencies_hz) else "Fig. 8"
        panels.append({"figure": figure, "frequency_hz": case.frequency_hz,
                       "limit_mA": case.limit_ma, "title": case.title, "mpc": rows, "pid": pid,
                       "saturated": any(row["peak_requested_mA"] >= case.limit_ma
                                        for row in rows)})
    return panels


def fig5_and_6(c: ServoConditions, done: dict[str, Session]
               ) -> tuple[dict[str, Any], dict[str, Any]]:
    """Fig. 5 (FOH at H_t = ``fig5_ht``) and Fig. 6 (PID) on the 10 Hz sine: at the paper's
    current limit and at the rated current."""
    at_limit = SineCase(c.fast.frequency_hz, c.limit_ma).name
    fig5 = {"paper": PAPER_FIG5, "ht": c.fig5_ht,
            "limit": tracking(done[f"{at_limit}/foh/{c.fig5_ht}"]),
            "rated": tracking(done[f"{c.fast.name}/foh/{c.fig5_ht}"])}
    fig6 = {"paper": PAPER_FIG6, "limit": tracking(done[f"{at_limit}/pid"]),
            "rated": tracking(done[f"{c.fast.name}/pid"])}
    return fig5, fig6


def waterfall(c: ServoConditions, done: dict[str, Session]) -> dict[str, Any]:
    """Figs. 9-10 at H_t = H_u = ``waterfall_ht`` on the 10 Hz sine at the rated current:
    per ERT, the predicted input at the end of the control horizon û(k+H_u-1|k) against the
    current applied at that tick (mean |.| ratio: ZOH's near 0 per the paper), and how far
    the predicted inputs are from the applied ones (RMS, relative to the applied RMS)."""
    out: dict[str, Any] = {"ht": c.waterfall_ht}
    for ert in ("zoh", "foh"):
        session = done[f"{c.fast.name}/{ert}/{c.waterfall_ht}"]
        out[ert] = {**prediction_match(session.mcap, c.settle_s, c.waterfall_ht),
                    "mcap": session.mcap}
    return out


def explicit_mpc(c: ServoConditions, laws: dict[int, Any], done: dict[str, Session],
                 echo: Callable[[str], None]) -> dict[str, Any]:
    """Section III-C: the law's figures per H_t, the box sweep, what each controller is, and
    the evaluation time of the law against the online QP (per call, and per step in the
    sessions)."""
    from hil.paper import servo_empc

    law = laws[c.empc_ht]
    count = 200 if c.quick else 1000
    thetas = servo_empc.closed_loop_thetas(law, c, count)
    evaluation = servo_empc.evaluation_times(law, thetas, repeat=1 if c.quick else 3)
    echo(f"explicit MPC evaluated on {len(thetas)} parameter vectors")
    steps = {kind: {scenario: done[f"{scenario}/{kind}"]["step_us"]
                    for scenario in ("trapezoid", "disturbance")} for kind in ("empc", "mpc")}
    return {
        "paper": servo_empc.PAPER_EMPC, "paper_sequential": servo_empc.PAPER_SEQUENTIAL,
        "paper_tree_ht": servo_empc.PAPER_TREE_HT, "ht": c.empc_ht,
        "hil": servo_empc.law_figures(law),
        "horizons": [servo_empc.law_figures(laws[h], with_region_tree=False)
                     for h in sorted(laws)],
        "box_sweep": servo_empc.box_sweep(c, echo),
        "controllers": servo_empc.describe_controllers(law),
        "evaluation": {**evaluation, "thetas": len(thetas)},
        "session_step_us": steps,
    }


def trapezoid(c: ServoConditions, done: dict[str, Session]) -> dict[str, Any]:
    """Figs. 14-15: the explicit MPC and the PID on the trapezoid (the online MPC beside)."""
    empc = done["trapezoid/empc"]
    return {"empc": {**tracking(empc), "controllers": controllers_used(empc.mcap),
                     "share_controller_1": share_in(empc.mcap, 1)},
            "pid": tracking(done["trapezoid/pid"]), "mpc": tracking(done["trapezoid/mpc"])}


def disturbance(c: ServoConditions, done: dict[str, Session]) -> dict[str, Any]:
    """Fig. 16: the explicit MPC against the push (:func:`push_response`), the controllers
    used during it, and both MPCs' KPIs."""
    empc = done["disturbance/empc"]
    return {**push_response(empc.mcap, c.push_end_s),
            "during": controllers_used(empc.mcap, c.push_start_s, c.push_end_s),
            "mpc": tracking(done["disturbance/mpc"]), "empc": tracking(empc)}


def conditions_of(c: ServoConditions) -> dict[str, Any]:
    """The conditions as the JSON and the report show them."""
    return {key: (list(value) if isinstance(value, tuple) else value)
            for key, value in vars(c).items()}
