"""The servo paper's report: the results of :func:`hil.paper.servo.measure` as the tables and
figures of :mod:`hil.paper.report`, each keyed by the paper's name for it, the paper's value
beside hil's where the paper gives one, and the differences explained by the sweeps.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hil.controllers.servo.model import published_axis_model
from hil.controllers.servo.pid import EQ16_QUALITY, notch_coefficients, resonance_hz
from hil.paper import servo_figures
from hil.paper.report import (
    Compared,
    Figure,
    PaperOptions,
    PaperReport,
    Section,
    Table,
    comparison_table,
)
from hil.paper.servo_conditions import SOURCE as CONDITIONS
from hil.paper.servo_conditions import ServoConditions

TITLE = ("Model Predictive Control for Reference Tracking on an Industrial Machine Tool Servo "
         "Drive: reproduced by hil")
PAPER = ("M. A. Stephens, C. Manzie and M. C. Good, \"Model Predictive Control for Reference "
         "Tracking on an Industrial Machine Tool Servo Drive\", IEEE Trans. Ind. Informatics "
         "9(2), 2013")
#: the paper's tables and figures with a result (Figs. 2, 3 and 11 are photographs), and the
#: figures of its text (sections III-C/D), the statements it makes and the differences
EXPECTED = ("Conditions", "Table I", "Fig. 1", "Fig. 4", "Figs. 5-6", "Fig. 5", "Fig. 6",
            "Fig. 7", "Fig. 8", "Figs. 9-10", "Fig. 9", "Fig. 10", "Fig. 12", "Fig. 13",
            "Sec. III-D", "Sec. III-C", "Evaluation time", "Figs. 14-15", "Fig. 14", "Fig. 15",
            "Fig. 16", "Statements", "Differences")
PHOTOGRAPHS = {"Fig. 2": "the 5-axis tool and cutter grinder", "Fig. 3": "its headstock axis "
               "with a large workpiece", "Fig. 11": "the machine's digital servo drives"}


def report_of(results: dict[str, Any], c: ServoConditions,
              options: PaperOptions) -> PaperReport:
    """The report of ``results`` (figures drawn into ``options.figures``)."""
    options.figures.mkdir(parents=True, exist_ok=True)
    sections = [
        Section("What was run", (intro(c), conditions_table(c), table_i(c))),
        Section("Figs. 5-6: tracking the 10 Hz sine", figs_5_6(results, c, options)),
        Section("Figs. 7-8: error against the trajectory horizon", figs_7_8(results, options)),
        Section("Figs. 9-10: predicted and applied currents", figs_9_10(results, options)),
        Section("The explicit MPC (sections III-C and III-D)", explicit(results)),
        Section("Figs. 14-16: on the emulated drive", figs_14_16(results, c, options)),
        Section("Figs. 1, 4, 12 and 13: the method", method(options)),
        Section("The paper's statements, checked", (statements(results),)),
        Section("The differences, explained by measurement", differences(results, c, options)),
    ]
    return PaperReport("servo", TITLE, PAPER, EXPECTED, sections, results, options.quick)


def _png(options: PaperOptions, name: str) -> Any:
    return options.figures / f"{name}.png"


def _f(value: float | None, digits: int = 4) -> str:
    return "–" if value is None else f"{value:.{digits}g}"


# -- what was run ---------------------------------------------------------------------------


def intro(c: ServoConditions) -> str:
    return (
        f"Every result below comes from a lockstep session of `hil servo run` on hil's "
        f"emulated drive (the paper's published axis model behind a CiA 402 node on a CAN "
        f"bus), recorded to MCAP in `servo/sessions/`. The conditions are read from "
        f"`{CONDITIONS}`: where the paper states one it is used as stated; where the paper is "
        f"silent, the table says what hil chose and why. Photographs have nothing to reproduce: "
        + "; ".join(f"{key} shows {what}" for key, what in PHOTOGRAPHS.items()) + ".")


def conditions_table(c: ServoConditions) -> Table:
    model = published_axis_model()
    rows = (
        ("sample period T", "500 us", f"{c.cycle_period_us} us", "the SYNC period"),
        ("plant", "4th-order headstock model (III-A)", "the printed model, in the emulated "
         "drive and in the controllers", f"resonance {resonance_hz(model):.0f} Hz"),
        ("input constraint", "±1000 mA", f"±{c.limit_ma:g} mA; the 10 Hz sine also at "
         f"±{c.rated_ma:g} mA", "the printed model needs more than 1000 mA for it "
         "(see the differences)"),
        ("Q(i), R(i)", "10^6, 1", f"{c.q:g}, {c.r:g}", ""),
        ("H_p", "50", str(c.hp), ""),
        ("H_t = H_u", "1-8 (Figs. 7-8), 8 (Fig. 5), 4 (Figs. 9-10), 3 (EMPC)",
         f"{', '.join(map(str, c.horizons))}; {c.fig5_ht}; {c.waterfall_ht}; {c.empc_ht}", ""),
        ("sine", "2 deg at 1 Hz and 10 Hz", f"{c.amplitude_deg:g} deg at "
         f"{', '.join(f'{f:g}' for f in c.frequencies_hz)} Hz", ""),
        ("error metric", "sum of |error| over one complete cycle, normalised to set-point MPC",
         f"the same, over {c.cycles:g} cycle(s) after {c.settle_s:g} s", "silent on the "
         "start: hil leaves the start-up transient (the PID's integrator) out"),
        ("trapezoid", "270 deg at 60 r/min", f"{c.stroke_deg:g} deg at {c.speed_rpm:g} r/min, "
         f"{c.acceleration_deg_s2:g} deg/s²", "silent on the acceleration: hil's needs about "
         "350 mA, 'well within the input limits' as the paper says of its run"),
        ("disturbance", "a large position disturbance, removed at 0.35 s", f"{c.torque_ma:g} "
         f"mA of load torque from {c.push_start_s:g} s to {c.push_end_s:g} s", "silent on its "
         "size: a push the ±1000 mA cannot resist, as a hand on the headstock"),
        ("state estimate", "a Kalman filter", "steady-state Kalman filter on the velocity "
         "form", "silent on its tuning; the emulator adds no measurement noise"),
        ("EMPC parameter box", "not given", "hil's default box (controllers/servo/empc.py)",
         "swept below"),
        ("PID", "Table I, notch (16)", "Table I; notch (16) as hil's PID reads it", "eq. (16) "
         "used literally at 500 us notches 48 Hz and is unstable with Table I's gains; hil "
         "centres it on the resonance with its printed Q"),
    )
    return Table("Conditions", "the paper's conditions and hil's", ("", "paper", "hil", "note"),
                 rows)


def table_i(c: ServoConditions) -> Table:
    model = published_axis_model()
    center = resonance_hz(model)
    b, a = notch_coefficients(center, EQ16_QUALITY, model.dt)
    rows = (
        ("K_pos [RPM/deg]", "3.6111", f"{c.k_pos_rpm_per_deg:g}"),
        ("K_vel [A/RPM]", "0.4444", f"{c.k_vel_a_per_rpm:g}"),
        ("T_i [us]", "2000", f"{c.ti_us:g}"),
        ("notch (16), numerator", "0.9352 (z² - 1.9774 z + 1)",
         f"{b[0]:.4f} (z² {b[1] / b[0]:+.4f} z + 1): zeros at {center:.0f} Hz"),
        ("notch (16), denominator", "z² - 1.8492 z + 0.8651",
         f"z² {a[1]:+.4f} z {a[2]:+.4f}: unit DC gain, Q = {EQ16_QUALITY:.2f} as printed"),
    )
    return Table("Table I", "the cascaded PID's tuning and notch, as run",
                 ("parameter", "paper", "hil"), rows)


# -- Figs. 5-10 -----------------------------------------------------------------------------


def figs_5_6(results: dict[str, Any], c: ServoConditions,
             options: PaperOptions) -> tuple[Any, ...]:
    fig5, fig6 = results["fig5"], results["fig6"]
    limit, rated = f"±{c.limit_ma:g} mA", f"±{c.rated_ma:g} mA"
    cells = []
    for name, fig, what in (("Fig. 5", fig5, f"MPC FOH H_t = H_u = {c.fig5_ht}"),
                            ("Fig. 6", fig6, "cascaded PID")):
        for case, label in (("limit", limit), ("rated", rated)):
            row = fig[case]
            bound = c.limit_ma if case == "limit" else c.rated_ma
            note = ("saturated: held at the limit" if row["peak_requested_mA"] >= bound
                    else f"peak {row['peak_current_mA']:.0f} mA")
            cells += [Compared(f"{name}: {what}, max error [deg], {label}",
                               fig["paper"]["max_error_deg"], row["max_error_deg"], note),
                      Compared(f"{name}: {what}, max error [% of amplitude], {label}",
                               fig["paper"]["max_error_pct"], row["max_error_pct"]),
                      Compared(f"{name}: {what}, RMS error [deg], {label}", None,
                               row["rms_error_deg"], "the paper gives none")]
    frequency = max(c.frequencies_hz)
    session = results["sessions"]
    at_limit = session[f"{frequency:g}hz-{c.limit_ma:g}ma/foh/{c.fig5_ht}"]
    servo_figures.tracking(str(_png(options, "fig05")), f"Fig. 5: MPC FOH-ERT, H_t = H_u = "
                           f"{c.fig5_ht}, H_p = {c.hp}, {frequency:g} Hz sine, {rated}",
                           session[f"{c.fast.name}/foh/{c.fig5_ht}"], c.settle_s,
                           {f"error at {limit} (saturated)": at_limit})
    servo_figures.tracking(str(_png(options, "fig06")), f"Fig. 6: cascaded PID (Table I), "
                           f"{frequency:g} Hz sine, {rated}", session[f"{c.fast.name}/pid"],
                           c.settle_s)
    return (comparison_table("Figs. 5-6", f"max tracking error on the {c.amplitude_deg:g} deg, "
                             f"{frequency:g} Hz sine", cells),
            Figure("Fig. 5", "simulated tracking, MPC with FOH-ERT", _png(options, "fig05"),
                   "Reference and position, then the error, of the session at the rated "
                   "current; dashed, the error at the paper's ±1000 mA, where the MPC "
                   "saturates."),
            Figure("Fig. 6", "simulated tracking, cascaded PID", _png(options, "fig06")))


def figs_7_8(results: dict[str, Any], options: PaperOptions) -> tuple[Any, ...]:
    parts: list[Any] = []
    for panel in results["sine"]:
        key = panel["figure"] if panel["figure"] not in [p.key for p in parts
                                                         if isinstance(p, Table)] \
            else f"{panel['figure']} ({panel['limit_mA']:g} mA)"
        by = {(row["ert"], row["ht"]): row for row in panel["mpc"]}
        rows = []
        for ht in sorted({row["ht"] for row in panel["mpc"]}):
            zoh, foh = by.get(("zoh", ht)), by.get(("foh", ht))
            rows.append((ht, *(_kpi_cells(zoh)), *(_kpi_cells(foh))))
        pid = panel["pid"]
        rows.append(("PID", pid["max_error_deg"], pid["rms_error_deg"], pid["normalised"],
                     None, None, None))
        note = " (saturated: the MPCs ask more than the limit)" if panel["saturated"] else ""
        parts.append(Table(key, f"{panel['title']}{note}: max and RMS error [deg], cumulative "
                           "|error| normalised to set-point MPC (ZOH, H_t = 1)",
                           ("H_t = H_u", "ZOH max", "ZOH RMS", "ZOH norm.", "FOH max",
                            "FOH RMS", "FOH norm."), tuple(rows)))
    fig7 = [p for p in results["sine"] if p["figure"] == "Fig. 7"]
    fig8 = [p for p in results["sine"] if p["figure"] == "Fig. 8"]
    servo_figures.normalised_errors(str(_png(options, "fig07")), fig7)
    servo_figures.normalised_errors(str(_png(options, "fig08")), fig8)
    parts += [
        "The paper draws these as curves without printing their values; what it says of them "
        "is checked in *The paper's statements* below.",
        Figure("Fig. 7", "normalised cumulative error, 1 Hz sine", _png(options, "fig07")),
        Figure("Fig. 8", "normalised cumulative error, 10 Hz sine", _png(options, "fig08"),
               "At the paper's ±1000 mA every MPC saturates on the printed model; at the rated "
               "current none does."),
    ]
    return tuple(parts)


def _kpi_cells(row: dict[str, Any] | None) -> tuple[Any, ...]:
    if row is None:
        return (None, None, None)
    return (row["max_error_deg"], row["rms_error_deg"], row["normalised"])


def figs_9_10(results: dict[str, Any], options: PaperOptions) -> tuple[Any, ...]:
    w = results["waterfall"]
    rows = tuple((ert.upper(), w[ert]["end_ratio"], w[ert]["mismatch"], w[ert]["ticks"])
                 for ert in ("zoh", "foh"))
    for number, ert in ((9, "zoh"), (10, "foh")):
        servo_figures.waterfalls(str(_png(options, f"fig{number:02d}")), {
            f"Fig. {number}: MPC {ert.upper()}-ERT, H_t = H_u = {w['ht']}": w[ert]["mcap"]})
    return (Table("Figs. 9-10", f"H_t = H_u = {w['ht']}: the predicted input at the end of the "
                  "control horizon against the current applied then (mean |û(k+H_u-1|k)| / mean "
                  "|u(k+H_u-1)|; the paper: ZOH's ≈ 0), and the predicted inputs' RMS distance "
                  "from the applied ones, relative to the applied RMS",
                  ("ERT", "end / applied", "predicted - applied", "ticks"), rows),
            Figure("Fig. 9", "waterfall, ZOH-ERT", _png(options, "fig09")),
            Figure("Fig. 10", "waterfall, FOH-ERT", _png(options, "fig10")))


# -- the explicit MPC -----------------------------------------------------------------------


def explicit(results: dict[str, Any]) -> tuple[Any, ...]:
    e = results["empc"]
    paper, hil = e["paper"], e["hil"]
    quick = results["quick"]
    note = f"H_t = H_u = {e['ht']} (--quick), not the paper's 3" if quick else ""
    cells = [Compared("regions", paper["regions"], hil["regions"], note),
             Compared("controllers", paper["controllers"], hil["controllers"]),
             Compared("tree nodes", paper["tree_nodes"], hil["tree_nodes"],
                      "hil's tree separates controllers"),
             Compared("tree depth", paper["tree_depth"], hil["tree_depth"]),
             Compared("tree over regions: nodes", paper["tree_nodes"],
                      hil["region_tree_nodes"], "one leaf label per region"),
             Compared("tree over regions: depth", paper["tree_depth"],
                      hil["region_tree_depth"])]
    horizons = tuple((row["ht"], row["regions"], row["controllers"], row["tree_nodes"],
                      row["tree_depth"], row["hyperplanes"], row["sequential_facets"],
                      row["build_s"]) for row in e["horizons"])
    ev, steps = e["evaluation"], e["session_step_us"]
    timing = [(name, ev[key]["p50"], ev[key]["p99"]) for key, name in (
        ("tree", "explicit law, tree descent (Python)"),
        ("sequential", "explicit law, sequential search over the regions (Python)"),
        ("online", f"online QP, daqp (QP path on {ev['online']['qp_share']:.0%} of them)"))]
    for kind, name in (("empc", "explicit MPC"), ("mpc", "online MPC")):
        for scenario in ("trapezoid", "disturbance"):
            step = steps[kind][scenario]
            timing.append((f"{name}, whole controller step in the {scenario} session",
                           step["median"], step["p99"]))
    controllers = "; ".join(f"#{i + 1}: {what}" for i, what in enumerate(e["controllers"]))
    return (
        comparison_table("Sec. III-D", f"the explicit MPC (FOH, H_t = H_u = {e['ht']}, "
                         "H_p = 50, ±1000 mA)", cells),
        f"The controllers (eq. 15's affine laws, numbered as the paper numbers them): "
        f"{controllers}.",
        Table("Sec. III-C", "the explicit law at each H_t = H_u (the paper: sequential search "
              f"out of reach above {e['paper_sequential']['ht']}, more than "
              f"{e['paper_sequential']['regions']} regions or about "
              f"{e['paper_sequential']['hyperplanes']} hyperplanes; the tree up to "
              f"{e['paper_tree_ht']})", ("H_t = H_u", "regions", "controllers", "tree nodes",
                                         "depth", "hyperplanes", "facets, sequential",
                                         "build [s]"), horizons),
        Table("Evaluation time", f"Δu(0|k) per call on {ev['thetas']} closed-loop parameter "
              "vectors, and the controller's whole step (Kalman filter and law) in the "
              "sessions [us]; Python on this machine, shared with other work (the p99 shows "
              "it): the paper gives no time, only that its DSP could not solve the QP online "
              "within T = 500 us",
              ("", "p50", "p99"), tuple(timing)),
    )


def figs_14_16(results: dict[str, Any], c: ServoConditions,
               options: PaperOptions) -> tuple[Any, ...]:
    t, d, session = results["trapezoid"], results["disturbance"], results["sessions"]
    servo_figures.explicit_run(str(_png(options, "fig14")), f"Fig. 14: explicit MPC, FOH-ERT, "
                               f"H_t = H_u = {c.empc_ht}, trapezoid {c.stroke_deg:g} deg at "
                               f"{c.speed_rpm:g} r/min", session["trapezoid/empc"], c.limit_ma)
    servo_figures.tracking(str(_png(options, "fig15")), f"Fig. 15: cascaded PID, trapezoid "
                           f"{c.stroke_deg:g} deg at {c.speed_rpm:g} r/min",
                           session["trapezoid/pid"], 0.0)
    servo_figures.explicit_run(str(_png(options, "fig16")), f"Fig. 16: explicit MPC, "
                               f"H_t = H_u = {c.empc_ht}, a push of {c.torque_ma:g} mA from "
                               f"{c.push_start_s:g} s to {c.push_end_s:g} s",
                               session["disturbance/empc"], c.limit_ma,
                               (c.push_start_s, c.push_end_s))
    rows = tuple((name, row["max_error_deg"], row["rms_error_deg"], row["peak_current_mA"])
                 for name, row in (("explicit MPC (Fig. 14)", t["empc"]),
                                   ("cascaded PID (Fig. 15)", t["pid"]),
                                   ("online MPC, same H_t", t["mpc"])))
    push = (("displacement by the push [deg]", d["push_deg"]),
            ("overshoot after the release [deg]", d["overshoot_deg"]),
            ("settled (|error| < 1 % of the push) at [s]", d["settled_s"]),
            ("error at the end [deg]", d["final_error_deg"]),
            ("controllers used during the push", ", ".join(f"#{k}" for k in d["during"])),
            ("controllers used after the release", ", ".join(f"#{k}" for k in d["after"])))
    return (
        Table("Figs. 14-15", f"the trapezoid on the emulated drive (the paper gives no "
              f"figures; the explicit MPC used controller(s) "
              f"{', '.join(f'#{k}' for k in t['empc']['controllers'])}, #1 on "
              f"{t['empc']['share_controller_1']:.0%} of the ticks)",
              ("", "max error [deg]", "RMS error [deg]", "peak current [mA]"), rows),
        Figure("Fig. 14", "the explicit MPC on the trapezoid", _png(options, "fig14"),
               "Bottom: the controller of every tick, recorded on `/empc/controller`."),
        Figure("Fig. 15", "the cascaded PID on the trapezoid", _png(options, "fig15")),
        Table("Fig. 16", "the explicit MPC rejecting a position disturbance", ("", "hil"), push),
        Figure("Fig. 16", "the explicit MPC rejecting a position disturbance",
               _png(options, "fig16"), "Shaded: the push."),
    )


def method(options: PaperOptions) -> tuple[Any, ...]:
    model = published_axis_model()
    servo_figures.horizons(str(_png(options, "fig01")))
    servo_figures.bode(str(_png(options, "fig04")), model, resonance_hz(model))
    pid_blocks = (
        ("position controller", "P, K_pos", "P, K_pos (controllers/servo/pid.py)"),
        ("velocity controller", "PI, K_vel, T_i", "PI, anti-windup by conditional integration"),
        ("velocity feedback", "from the encoder", "backward difference of the position"),
        ("current reference filter", "notch (16)", "notch on the model's resonance"),
        ("current controller", "the drive's", "the emulated drive's (ideal) current loop"),
    )
    mpc_blocks = (
        ("state estimate", "Kalman filter", "steady-state Kalman filter (velocity form)"),
        ("optimiser", "online QP or explicit law (binary tree)",
         "daqp (online) or the explicit law's tree (controllers/servo/empc*.py)"),
        ("reference", "r(1..H_t|k) from the CNC", "the run's reference sampled each tick"),
        ("current limit", "in the MPC constraints (10)", "in the constraints and clamped again "
         "in the driver"),
        ("notch filter", "disabled", "none"),
    )
    return (
        Figure("Fig. 1", "MPC horizons and the extended reference (hil's own matrices)",
               _png(options, "fig01")),
        Figure("Fig. 4", "frequency response of the headstock model (the emulator's plant)",
               _png(options, "fig04")),
        Table("Fig. 12", "the cascaded PID's structure, block by block", ("block", "paper",
                                                                          "hil"), pid_blocks),
        Table("Fig. 13", "the MPC's structure, block by block", ("block", "paper", "hil"),
              mpc_blocks),
    )


def statements(results: dict[str, Any]) -> Table:
    rows = tuple((row["where"], row["claim"], row["measured"],
                  "yes" if row["holds"] else "no" if row["holds"] is False else "not judged")
                 for row in results["claims"])
    return Table("Statements", "what the paper says of its results, held against hil's "
                 "sessions", ("where", "the paper says", "hil measured", "holds"), rows)


# -- the differences ------------------------------------------------------------------------


def differences(results: dict[str, Any], c: ServoConditions,
                options: PaperOptions) -> tuple[Any, ...]:
    x = results["explain"]
    fig5, fig6 = results["fig5"]["paper"], results["fig6"]["paper"]
    e = results["empc"]
    panels = [
        {"x": [r["limit_mA"] for r in x["current"]], "y": [r["max_error_deg"]
                                                            for r in x["current"]],
         "paper": fig5["max_error_deg"], "xlabel": "current limit [mA]", "logy": True,
         "ylabel": "max error [deg]", "title": f"Fig. 5: FOH H_t = {c.fig5_ht}, limit"},
        {"x": [r["r"] for r in x["r"]], "y": [r["max_error_deg"] for r in x["r"]],
         "paper": fig5["max_error_deg"], "xlabel": "R (Q = 1e6)", "logx": True, "logy": True,
         "ylabel": "max error [deg]", "title": f"Fig. 5: FOH H_t = {c.fig5_ht}, R"},
        {"x": [r["vff"] for r in x["vff"]], "y": [r["max_error_deg"] for r in x["vff"]],
         "paper": fig6["max_error_deg"], "xlabel": "velocity feed-forward share",
         "ylabel": "max error [deg]", "title": "Fig. 6: PID feed-forward", "logy": True},
        {"x": [r["scale"] for r in x["box"]], "y": [r["regions"] for r in x["box"]],
         "paper": e["paper"]["regions"], "xlabel": "parameter box (x default)", "logx": True,
         "ylabel": "regions", "title": f"EMPC H_t = H_u = {e['ht']}: regions"},
    ]
    servo_figures.explanations(str(_png(options, "differences")), panels)
    current = tuple((r["limit_mA"], r["max_error_deg"], r["rms_error_deg"],
                     r["peak_requested_mA"]) for r in x["current"])
    r_rows = tuple((r["r"], (1.0 / r["r"]) ** 0.5, r["max_error_deg"], r["rms_error_deg"],
                    r["peak_current_mA"]) for r in x["r"])
    vff_rows = tuple((r["vff"], r["max_error_deg"], r["rms_error_deg"], r["peak_current_mA"])
                     for r in x["vff"])
    push_rows = tuple((r["start_s"], r["push_deg"], r["overshoot_deg"],
                       ", ".join(f"#{k}" for k in r["after"])) for r in x["push"])
    friction_rows = tuple(("none" if r["tau_s"] is None else r["tau_s"],
                           r["zoh"]["end_ratio"], r["zoh"]["mismatch"], r["foh"]["end_ratio"],
                           r["foh"]["mismatch"]) for r in x["friction"])
    box_rows = tuple((r["scale"], r["regions"], r["controllers"], r["tree_nodes"],
                      r["tree_depth"], r["region_tree_nodes"], r["region_tree_depth"])
                     for r in x["box"])
    return (
        fig5_text(results, c),
        Table("Fig. 5 and the current limit", f"MPC FOH H_t = H_u = {c.fig5_ht}, "
              f"{max(c.frequencies_hz):g} Hz sine, at each current limit",
              ("limit [mA]", "max error [deg]", "RMS error [deg]", "current asked [mA]"),
              current),
        Table("Fig. 5 and R", f"the same at ±{c.rated_ma:g} mA for each R: R stands for a "
              "plant s = 1/√R times lighter than printed", ("R", "s", "max error [deg]",
                                                             "RMS error [deg]",
                                                             "peak current [mA]"), r_rows),
        fig6_text(results),
        Table("Fig. 6 and feed-forward", f"the Table I PID with a share of velocity "
              f"feed-forward, {max(c.frequencies_hz):g} Hz sine, ±{c.rated_ma:g} mA",
              ("share", "max error [deg]", "RMS error [deg]", "peak current [mA]"), vff_rows),
        empc_text(results),
        Table("Sec. III-D and the box", f"the explicit law (H_t = H_u = {e['ht']}) over a "
              "parameter box scaled from hil's default", ("scale", "regions", "controllers",
                                                          "tree nodes", "depth",
                                                          "region tree nodes",
                                                          "region tree depth"), box_rows),
        push_text(results),
        Table("Fig. 16 and the push", f"the explicit MPC (H_t = H_u = {e['ht']}) against a "
              f"push of {c.torque_ma:g} mA ending at {c.push_end_s:g} s, started earlier for a "
              "larger displacement", ("push from [s]", "displacement [deg]",
                                      "overshoot [deg]", "controllers after the release"),
              push_rows),
        frequency_text(results, c),
        waterfall_text(results),
        Table("Figs. 9-10 and friction", f"the waterfall metrics (H_t = H_u = "
              f"{c.waterfall_ht}, {max(c.frequencies_hz):g} Hz, ±{c.rated_ma:g} mA) with viscous "
              "friction of time constant tau in the model and the plant (offline)",
              ("tau [s]", "ZOH end / applied", "ZOH predicted - applied", "FOH end / applied",
               "FOH predicted - applied"), friction_rows),
        Figure("Differences", "the sweeps, with the paper's figure as a dashed line",
               _png(options, "differences")),
    )


def fig5_text(results: dict[str, Any], c: ServoConditions) -> str:
    x, fig5 = results["explain"], results["fig5"]
    paper = fig5["paper"]["max_error_deg"]
    match = x["r_match"]
    swept = [r["r"] for r in x["r"]]
    where = (f"the paper's {paper:g} deg is met at R ≈ {match:.2g}, i.e. on a plant "
             f"{(1 / match) ** 0.5:.2g} times lighter than printed" if match is not None
             else f"the paper's {paper:g} deg is not met between R = {min(swept):g} and "
             f"{max(swept):g}")
    return (
        f"**Fig. 5.** On the printed model the {max(c.frequencies_hz):g} Hz sine asks for "
        f"{x['needed_mA']:.0f} mA at its peak, {x['lighter_by']:.2f} times the paper's "
        f"±{c.limit_ma:g} mA: at that limit every MPC saturates (max error "
        f"{fig5['limit']['max_error_deg']:.3g} deg), so the paper's own simulation cannot "
        f"have run the printed model at that limit without saturating. Its plant must have "
        f"been at least {x['lighter_by']:.2f} times lighter (rounding to two digits leaves the "
        f"gain open). With the current unlimited (±{c.rated_ma:g} mA) hil's error is "
        f"{fig5['rated']['max_error_deg']:.3g} deg. The error's size is set by R against the "
        f"current moves the plant needs: a plant s times lighter acts as the printed one with "
        f"R / s² and s times the current, so the R sweep is a sweep of the plant's gain: "
        f"{where}. A plant just light enough for ±{c.limit_ma:g} mA is R = "
        f"{x['r_equivalent']:.2g} on this scale.")


def fig6_text(results: dict[str, Any]) -> str:
    x, fig6 = results["explain"], results["fig6"]
    paper = fig6["paper"]["max_error_deg"]
    ends = (x["vff"][0]["max_error_deg"], x["vff"][-1]["max_error_deg"])
    where = (f"the paper's {paper:g} deg is met at a share of {x['vff_match']:.2f}"
             if x["vff_match"] is not None else f"the paper's {paper:g} deg is not met between "
             f"{ends[0]:.3g} and {ends[1]:.3g} deg")
    return (
        f"**Fig. 6.** Table I's cascade has no feed-forward: its position loop (K_pos = "
        f"3.6111 RPM/deg, 21.7 /s) lags a 10 Hz sine by most of its amplitude "
        f"({fig6['rated']['max_error_deg']:.3g} deg). A drive's PID normally adds the "
        f"reference's velocity; the paper neither gives nor excludes it. Swept from none to "
        f"all of it, the error goes from {ends[0]:.3g} to {ends[1]:.3g} deg: {where}.")


def empc_text(results: dict[str, Any]) -> str:
    e = results["empc"]
    paper = e["paper"]
    at_paper = [r for r in e["box_sweep"] if r["regions"] == paper["regions"]]
    found = (f"with a box {at_paper[0]['scale']:g} times hil's default the law has "
             f"{at_paper[0]['regions']} regions, {at_paper[0]['controllers']} controllers and a "
             f"tree of depth {at_paper[0]['tree_depth']}" if at_paper
             else "no box of the sweep gives the paper's region count")
    depth = paper["tree_depth"]
    return (
        f"**Sec. III-D.** The controllers are the law itself ({e['hil']['controllers']} against "
        f"the paper's {paper['controllers']}); the regions are how the parameter space is cut "
        f"up, and that depends on the box the law is computed over, which the paper does not "
        f"give: {found}. The paper's {paper['tree_nodes']} nodes are 2^{depth} - 1, a complete "
        f"binary tree of depth {depth} (a search tree stored as a full array); hil's trees "
        f"keep only the nodes they need, {e['hil']['tree_nodes']} separating controllers and "
        f"{e['hil']['region_tree_nodes']} separating regions.")


def push_text(results: dict[str, Any]) -> str:
    rows = sorted(results["explain"]["push"], key=lambda r: r["push_deg"])
    counts = [(r["push_deg"], len([k for k in r["after"] if k > 0])) for r in rows]
    few = [deg for deg, n in counts if n <= 3]
    many = [deg for deg, n in counts if n > 3]
    if few and many:
        where = (f"up to {max(few):.3g} deg it needs three or fewer, the paper's count; from "
                 f"{min(many):.3g} deg on more")
    elif few:
        where = "every push of the sweep leaves it with three controllers or fewer"
    else:
        where = "no push of the sweep leaves it with the paper's three or fewer"
    d = results["disturbance"]
    return (
        "**Fig. 16.** The paper does not say how large its push was. The explicit MPC needs "
        "more controllers after the release the further the axis was pushed ("
        + ", ".join(f"{deg:.3g} deg: {n}" for deg, n in counts)
        + f"): {where}. hil's main push, chosen to be large, moved the axis "
        f"{d['push_deg']:.3g} deg and needs {len([k for k in d['after'] if k > 0])}.")


def frequency_text(results: dict[str, Any], c: ServoConditions) -> str:
    x = results["explain"]
    match = x["vff_match"]
    matched = x.get("pid_matched", {})
    if match is None or len(matched) < 2:
        return ("**Figs. 7-8, the PID.** No feed-forward share of the sweep matches Fig. 6, so "
                "the PID of the paper's Figs. 7-8 is not pinned down.")
    rows = ", ".join(f"{f} Hz: {row['max_error_deg']:.3g} deg" for f, row in matched.items())
    return (
        f"**Figs. 7-8, the PID.** hil's Table I PID lags the 1 Hz sine too (no feed-forward), "
        f"so against it the MPC gains most at 1 Hz, where the paper says it gains most at "
        f"10 Hz. With the feed-forward share that matches Fig. 6 ({match:.2f}) the PID's max "
        f"error is {rows}; the statements table gives the MPC's advantage under both PIDs.")


def rigid_body_poles() -> list[float]:
    """|z| of the printed model's two real poles (both 1 for a rigid body without friction)."""
    poles = np.linalg.eigvals(published_axis_model().A)
    return sorted(float(abs(p)) for p in poles if abs(p.imag) < 1e-9)


def waterfall_text(results: dict[str, Any]) -> str:
    w, rows = results["waterfall"], results["explain"]["friction"]
    poles = " and ".join(f"{p:.7f}" for p in rigid_body_poles())
    swept = ", ".join(f"tau = {r['tau_s']:g} s: ZOH {r['zoh']['end_ratio']:.2f}, FOH "
                      f"{r['foh']['end_ratio']:.2f}" for r in rows if r["tau_s"] is not None)
    near_zero = [r for r in rows if r["zoh"]["end_ratio"] < 0.2]
    closer = all(r["foh"]["mismatch"] < r["zoh"]["mismatch"] for r in rows)
    verdict = ("with enough friction ZOH's held current does fall towards zero, as the paper "
               "says" if near_zero else "no friction of the sweep brings ZOH's held current "
               "near zero, so the paper's explanation does not carry over to this model and "
               "that half of the statement stays unreproduced")
    verdict += ("; FOH's predictions match the applied currents more closely than ZOH's at "
                "every friction, the other half" if closer else "; FOH's predictions do not "
                "match the applied currents more closely than ZOH's at every friction")
    return (
        f"**Figs. 9-10.** hil's ZOH plan ends holding {w['zoh']['end_ratio']:.0%} of the "
        f"current applied then (FOH {w['foh']['end_ratio']:.0%}), where the paper's ZOH ends "
        f"near zero. The paper explains that by the viscous friction of its plant model, "
        f"which the printed model lost in rounding (its real poles are at |z| = {poles}: a "
        f"free rigid body). Putting viscous friction back into both the MPC's model and the "
        f"plant (offline, `hil/paper/servo_friction.py`; end ratio without friction ZOH "
        f"{rows[0]['zoh']['end_ratio']:.2f}, FOH {rows[0]['foh']['end_ratio']:.2f}; {swept}): "
        f"{verdict}.")
