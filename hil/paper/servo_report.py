"""The servo paper's report: the results of :func:`hil.paper.servo.measure` as the tables and
figures of :mod:`hil.paper.report`, each keyed by the paper's name for it, the paper's value
beside hil's where the paper gives one, and the differences explained by the sweeps.
"""

from __future__ import annotations

from typing import Any

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
from hil.paper.servo_differences import differences

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
        Section("The paper's statements, checked", (
            "What the paper says of its results in words, held against the sessions: a "
            "statement that does not hold here is measured in *The differences* below.",
            statements(results))),
        Section("The differences, explained by measurement", differences(results, c, options)),
    ]
    return PaperReport("servo", TITLE, PAPER, EXPECTED, sections, results, options.quick)


def _png(options: PaperOptions, name: str) -> Any:
    return options.figures / f"{name}.png"


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
    note = (f"H_t = H_u = {e['ht']} (--quick), not the paper's 3" if quick else
            "over hil's default parameter box (the paper gives none; swept below)")
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
        "The whole step adds the Kalman filter and the step's bookkeeping to either law. On "
        "the trapezoid no constraint is active (Fig. 14: controller #1 throughout), so there "
        "the online MPC takes its unconstrained fast path, one matrix product, every tick.",
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
