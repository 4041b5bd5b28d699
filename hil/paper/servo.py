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

import math
import time
from collections.abc import Callable, Sequence
from itertools import pairwise
from typing import TYPE_CHECKING, Any

import numpy as np

from hil.core.recording.reader import read_session
from hil.paper.servo_conditions import ServoConditions, SineCase, load_conditions
from hil.paper.servo_friction import friction_sweep
from hil.paper.servo_runs import CONTROLLER_TOPIC, Run, Session, SessionRunner, mpc_params

if TYPE_CHECKING:
    from hil.paper.report import PaperOptions, PaperReport

#: the paper's figures quoted in its text (section III-B)
PAPER_FIG5 = {"max_error_deg": 0.0643, "max_error_pct": 3.2}
PAPER_FIG6 = {"max_error_deg": 0.5021, "max_error_pct": 25.1}
KPI_KEYS = ("max_error_deg", "max_error_pct", "rms_error_deg", "cumulative_error_deg",
            "peak_current_mA", "peak_requested_mA")


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


# -- the sessions ------------------------------------------------------------------------------


def sine_run(c: ServoConditions, case: SineCase, controller: str, ert: str = "foh",
             ht: int = 8, params: dict[str, float] | None = None) -> Run:
    """One run on a sine case: ``controller`` "mpc" (``ert``, ``ht``) or "pid", ``params``
    laid over the paper's (Q, R; Table I)."""
    changed = params or {}
    if controller == "mpc":
        label = f"mpc-{ert}-ht{ht}"
        what = f"{case.title}, MPC {ert.upper()} H_t = {ht}"
        given = mpc_params(c, **changed)
    else:
        label, what, given = "pid", f"{case.title}, PID", {**c.pid_params, **changed}
    extra = "".join(f"-{key}{value:g}" for key, value in sorted(changed.items()))
    what += "".join(f", {key} = {value:g}" for key, value in sorted(changed.items()))
    return Run(name=f"sine-{case.name}-{label}{extra}", what=what, controller=controller,
               reference=c.sine_spec(case.frequency_hz),
               duration_s=c.sine_duration_s(case.frequency_hz), limit_ma=case.limit_ma,
               settle_s=c.settle_s, ert=ert, ht=ht, params=given)


def plan(c: ServoConditions, law: Any) -> dict[str, Run]:
    """Every session, by the key the tables find it under."""
    from hil.paper.servo_runs import recorded_empc

    runs: dict[str, Run] = {}
    for case in c.sine_cases:
        for ht in c.horizons:
            runs[f"{case.name}/zoh/{ht}"] = sine_run(c, case, "mpc", "zoh", ht)
            if ht >= 2:
                runs[f"{case.name}/foh/{ht}"] = sine_run(c, case, "mpc", "foh", ht)
        runs[f"{case.name}/pid"] = sine_run(c, case, "pid")
    fast = c.fast
    for limit in c.sweep_current_ma:
        runs[f"current/{limit:g}"] = sine_run(c, SineCase(fast.frequency_hz, limit), "mpc",
                                              "foh", c.fig5_ht)
    for r in c.sweep_r:
        runs[f"r/{r:g}"] = sine_run(c, fast, "mpc", "foh", c.fig5_ht,
                                    None if r == c.r else {"r": r})
    for vff in c.sweep_vff:
        runs[f"vff/{vff:g}"] = sine_run(c, fast, "pid", params={"vff": vff} if vff else None)
    empc = recorded_empc(law)
    h = c.empc_ht
    for key, reference, duration in (
            ("trapezoid", c.trapezoid_spec, c.trapezoid_duration_s),
            ("disturbance", c.disturbance_spec, c.disturbance_duration_s)):
        for kind, name, controller in (("empc", "explicit", empc), ("mpc", "online", "mpc")):
            runs[f"{key}/{kind}"] = Run(
                name=f"{key}-{kind}-ht{h}", what=f"{key}, {name} MPC H_t = {h}",
                controller=controller, reference=reference, duration_s=duration,
                limit_ma=c.limit_ma, ht=h, params=mpc_params(c))
    for start in c.sweep_push_start_s:
        runs[f"push/{start:g}"] = runs["disturbance/empc"] if start == c.push_start_s else Run(
            name=f"disturbance-empc-ht{h}-start{start:g}", controller=empc,
            what=f"disturbance from {start:g} s, explicit MPC H_t = {h}",
            reference=c.push_spec(start), duration_s=c.disturbance_duration_s,
            limit_ma=c.limit_ma, ht=h, params=mpc_params(c))
    runs["trapezoid/pid"] = Run(name="trapezoid-pid", what="trapezoid, PID", controller="pid",
                                reference=c.trapezoid_spec, duration_s=c.trapezoid_duration_s,
                                limit_ma=c.limit_ma, params=c.pid_params)
    return runs


def tracking(session: Session) -> dict[str, Any]:
    """The KPIs the tables quote of one session."""
    row = {key: session[key] for key in KPI_KEYS}
    row["step_us"] = session["step_us"]
    return row


# -- Figs. 5-8 -----------------------------------------------------------------------------


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


# -- Figs. 9-10 ----------------------------------------------------------------------------


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


def prediction_match(mcap: str, settle_s: float, hu: int) -> dict[str, float]:
    """How the recorded predictions û(k+i|k), i < H_u, compare with the currents applied at
    k+i, over the ticks after ``settle_s`` whose horizon lies within the session."""
    data = read_session(mcap)
    command, prediction = data.arrays("/drive/command"), data.arrays("/mpc/prediction")
    applied = command["command_mA"].astype(float)
    period = float(command["t_s"][1] - command["t_s"][0])
    ticks = np.rint(prediction["t_s"] / period).astype(int)
    keep = (prediction["t_s"] >= settle_s - 1e-9) & (ticks + hu <= applied.size)
    predicted = np.asarray(prediction["u_mA"][keep], dtype=float)[:, :hu]
    realised = np.stack([applied[k:k + hu] for k in ticks[keep]])
    return {"end_ratio": float(np.mean(np.abs(predicted[:, -1])) /
                               np.mean(np.abs(realised[:, -1]))),
            "mismatch": float(np.sqrt(np.mean((predicted - realised) ** 2)) /
                              np.sqrt(np.mean(realised ** 2))),
            "ticks": int(keep.sum())}


# -- the explicit MPC and Figs. 14-16 ------------------------------------------------------


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


def controllers_used(mcap: str, start_s: float = 0.0, end_s: float = math.inf) -> list[int]:
    """The explicit MPC's controllers (paper numbering) over ticks in [start_s, end_s)."""
    used = read_session(mcap).arrays(CONTROLLER_TOPIC)
    window = (used["t_s"] >= start_s - 1e-9) & (used["t_s"] < end_s - 1e-9)
    return sorted({int(v) for v in used["controller"][window]})


def share_in(mcap: str, controller: int) -> float:
    used = read_session(mcap).arrays(CONTROLLER_TOPIC)["controller"]
    return float(np.mean(used == controller))


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


def push_response(mcap: str, end_s: float) -> dict[str, Any]:
    """How far a push that ends at ``end_s`` moved the axis, the overshoot after the release,
    when the axis settled again (|error| below 1 % of the displacement for good), and the
    explicit MPC's controllers after the release."""
    command = read_session(mcap).arrays("/drive/command")
    t, error = command["t_s"], command["error_deg"].astype(float)
    pushed = t < end_s - 1e-9
    peak_at = int(np.argmax(np.abs(error[pushed])))
    peak, direction = float(abs(error[peak_at])), float(np.sign(error[peak_at]))
    overshoot = float(max(0.0, np.max(-direction * error[~pushed])))
    outside = np.flatnonzero(np.abs(error) > 0.01 * peak)
    settled = float(t[outside[-1] + 1]) if outside.size and outside[-1] + 1 < t.size else None
    return {"push_deg": peak, "overshoot_deg": overshoot, "settled_s": settled,
            "final_error_deg": float(abs(error[-1])), "after": controllers_used(mcap, end_s)}


# -- the differences, explained ------------------------------------------------------------


def crossing(xs: Sequence[float], ys: Sequence[float], target: float) -> float | None:
    """Where the piecewise-linear curve through (xs, ys) first meets ``target``, or None."""
    for (x0, y0), (x1, y1) in pairwise(zip(xs, ys, strict=True)):
        if (y0 - target) * (y1 - target) <= 0 and y0 != y1:
            return x0 + (target - y0) * (x1 - x0) / (y1 - y0)
    return None


def vff_match(c: ServoConditions, done: dict[str, Session]) -> float | None:
    """The PID's feed-forward share at which its max error on the 10 Hz sine is the paper's
    Fig. 6 figure (interpolated in the sweep, two decimals), or None outside it."""
    match = crossing(c.sweep_vff, [done[f"vff/{v:g}"]["max_error_deg"] for v in c.sweep_vff],
                     PAPER_FIG6["max_error_deg"])
    return None if match is None else round(match, 2)


def matched_pid(c: ServoConditions, done: dict[str, Session],
                run: SessionRunner) -> dict[str, Session]:
    """The PID whose feed-forward share matches Fig. 6 (:func:`vff_match`) on every sine (the
    fast one at the rated current), run once the sweep has found the share."""
    share = vff_match(c, done)
    if share is None:
        return {}
    run.planned += len(c.frequencies_hz)
    cases = {f: c.fast if f == c.fast.frequency_hz else SineCase(f, c.limit_ma)
             for f in c.frequencies_hz}
    return {f"matched/{f:g}": run(sine_run(c, case, "pid", params={"vff": share}))
            for f, case in cases.items()}


def explain(c: ServoConditions, done: dict[str, Session],
            box_sweep: list[dict[str, Any]]) -> dict[str, Any]:
    """The sweeps, each with where the paper's figure falls on it:

    * ``current``: FOH at H_t = ``fig5_ht`` on the 10 Hz sine at each current limit (what the
      paper's ±1000 mA does to it on the printed model);
    * ``r``: the same at the rated current for each R: a plant s times lighter than printed
      behaves as the printed one with R / s² and s times the current, so R stands for the
      plant's gain the printed model's rounding leaves open;
    * ``vff``: the Table I PID with a share of velocity feed-forward (a drive's usual, which
      the paper neither gives nor excludes);
    * ``box``: the explicit law's regions, tree nodes and depth over the parameter box.
    """
    current = [{"limit_mA": lim, **tracking(done[f"current/{lim:g}"])}
               for lim in c.sweep_current_ma]
    needed = done[f"current/{max(c.sweep_current_ma):g}"]["peak_requested_mA"]
    r_rows = [{"r": r, **tracking(done[f"r/{r:g}"])} for r in c.sweep_r]
    vff_rows = [{"vff": v, **tracking(done[f"vff/{v:g}"])} for v in c.sweep_vff]
    lightest = needed / c.limit_ma  # how much lighter the plant must be for the paper's limit
    by_r = sorted(r_rows, key=lambda row: row["r"])
    return {
        "current": current, "needed_mA": needed, "lighter_by": lightest,
        "r_equivalent": 1.0 / lightest ** 2,
        "r": r_rows,
        "r_match": crossing([row["r"] for row in by_r], [row["max_error_deg"] for row in by_r],
                            PAPER_FIG5["max_error_deg"]),
        "vff": vff_rows,
        "vff_match": vff_match(c, done),
        "pid_matched": {f"{f:g}": tracking(done[f"matched/{f:g}"]) for f in c.frequencies_hz
                        if f"matched/{f:g}" in done},
        "box": box_sweep,
        "push": [{"start_s": start, **push_response(done[f"push/{start:g}"].mcap, c.push_end_s)}
                 for start in c.sweep_push_start_s],
    }


# -- the paper's statements, held against the measurements --------------------------------


def claims(c: ServoConditions, results: dict[str, Any]) -> list[dict[str, Any]]:
    """Each qualitative statement of the paper: where it is made, whether hil's sessions
    bear it out, and the figures that decide it."""
    out: list[dict[str, Any]] = []

    def claim(where: str, text: str, holds: bool | None, measured: str) -> None:
        """``holds`` None: not judged (the run does not make the paper's case)."""
        out.append({"where": where, "claim": text,
                    "holds": None if holds is None else bool(holds), "measured": measured})

    for panel in results["sine"]:
        if panel["saturated"]:
            continue
        zoh = [r for r in panel["mpc"] if r["ert"] == "zoh"]
        foh = [r for r in panel["mpc"] if r["ert"] == "foh"]
        falls = all(a["normalised"] > b["normalised"] for seq in (zoh, foh)
                    for a, b in pairwise(seq))
        claim(panel["figure"], f"{panel['title']}: the tracking error decreases as H_t "
              "increases", falls, "ZOH " + ", ".join(f"{r['normalised']:.3f}" for r in zoh)
              + "; FOH " + ", ".join(f"{r['normalised']:.3f}" for r in foh))
        pairs = [(z, f) for z in zoh for f in foh if z["ht"] == f["ht"] and f["ht"] <= 6]
        claim(panel["figure"], f"{panel['title']}: FOH-ERT beats ZOH-ERT for H_t <= 6",
              all(f["cumulative_error_deg"] < z["cumulative_error_deg"] for z, f in pairs),
              ", ".join(f"H_t={f['ht']}: {f['normalised']:.3f} < {z['normalised']:.3f}"
                        for z, f in pairs))
        pid = panel["pid"]["normalised"]
        for ert, seq in (("ZOH", zoh), ("FOH", foh)):
            above = [r for r in seq if r["ht"] > 3]
            beats = [r["ht"] for r in seq if r["normalised"] < pid]
            if above:
                claim(panel["figure"], f"{panel['title']}: for H_t > 3 the MPC ({ert}-ERT) "
                      "beats the PID", all(r["normalised"] < pid for r in above),
                      f"PID {pid:.4f}; {ert} beats it at H_t = "
                      f"{', '.join(map(str, beats)) or 'none'}")
    advantage = high_frequency_advantage(c, results)
    if advantage is not None:
        claim("Figs. 7-8", "the MPC's advantage over the PID is largest on the high-frequency "
              "sine", advantage["table_i"][1] > advantage["table_i"][0],
              advantage["measured"])
    w = results["waterfall"]
    claim("Figs. 9-10", "ZOH-ERT predicts û(H_u|k) ≈ 0; FOH-ERT's predicted inputs match "
          "the applied ones more closely", w["zoh"]["end_ratio"] < 0.5 * w["foh"]["end_ratio"]
          and w["foh"]["mismatch"] < w["zoh"]["mismatch"],
          f"|û(k+H_u-1|k)| / |u(k+H_u-1)|: ZOH {w['zoh']['end_ratio']:.2f}, FOH "
          f"{w['foh']['end_ratio']:.2f}; predicted vs applied RMS: ZOH "
          f"{w['zoh']['mismatch']:.2f}, FOH {w['foh']['mismatch']:.2f}")
    e = results["empc"]
    by_ht = {row["ht"]: row for row in e["horizons"]}
    seq = e["paper_sequential"]
    if seq["ht"] in by_ht:
        row = by_ht[seq["ht"]]
        claim("Sec. III-C", f"sequential search is within reach up to H_t = H_u = {seq['ht']} "
              f"(at most {seq['regions']} regions, about {seq['hyperplanes']} hyperplanes)",
              row["regions"] <= seq["regions"],
              f"H_t = {seq['ht']}: {row['regions']} regions, {row['sequential_facets']} facets")
    paper_law = e["ht"] == 3  # --quick builds a smaller law: the paper's counts do not apply
    claim("Sec. III-D", "the explicit law has 11 controllers",
          e["hil"]["controllers"] == e["paper"]["controllers"] if paper_law else None,
          f"{e['hil']['controllers']} controllers in {e['hil']['regions']} regions")
    t = results["trapezoid"]
    claim("Fig. 14", "on the trapezoid the current stays within the limits: the explicit MPC "
          "never leaves controller #1", t["empc"]["controllers"] == [1],
          f"controllers used: {t['empc']['controllers']}; peak "
          f"{t['empc']['peak_current_mA']:.0f} mA")
    claim("Fig. 15", "the PID's tracking error is much larger than the explicit MPC's",
          t["pid"]["max_error_deg"] > 5 * t["empc"]["max_error_deg"],
          f"max error PID {t['pid']['max_error_deg']:.4f} deg, explicit MPC "
          f"{t['empc']['max_error_deg']:.4f} deg")
    d = results["disturbance"]
    claim("Fig. 16", "after the release the position overshoots, then settles at the set-point",
          d["overshoot_deg"] > 0 and d["settled_s"] is not None,
          f"pushed {d['push_deg']:.2f} deg, overshoot {d['overshoot_deg']:.3f} deg, settled "
          f"at {d['settled_s']} s")
    claim("Fig. 16", "after the release only three controllers (#1, #2, #3) are used",
          len([k for k in d["after"] if k > 0]) <= 3 if paper_law else None,
          f"after the release: {', '.join(f'#{k}' for k in d['after'])}; during the push: "
          f"{', '.join(f'#{k}' for k in d['during'])}")
    return out


def high_frequency_advantage(c: ServoConditions, results: dict[str, Any]
                             ) -> dict[str, Any] | None:
    """The PID's cumulative error over the best MPC's (FOH at the largest H_t) on the slow
    sine and on the fast one at the rated current, for the Table I PID and for the PID whose
    feed-forward matches Fig. 6; None without both sines."""
    slow = [p for p in results["sine"] if p["frequency_hz"] == min(c.frequencies_hz)
            and p["limit_mA"] == c.limit_ma]
    fast = [p for p in results["sine"] if p["frequency_hz"] == c.fast.frequency_hz
            and p["limit_mA"] == c.rated_ma]
    if not slow or not fast or slow[0] is fast[0]:
        return None

    def best(panel: dict[str, Any]) -> float:
        foh = [r for r in panel["mpc"] if r["ert"] == "foh"]
        return float(foh[-1]["cumulative_error_deg"]) if foh else math.nan

    table_i = [p["pid"]["cumulative_error_deg"] / best(p) for p in (slow[0], fast[0])]
    measured = (f"PID / MPC FOH H_t = {max(c.horizons)}, cumulative error: "
                f"{table_i[0]:.3g} at {slow[0]['title']}, {table_i[1]:.3g} at {fast[0]['title']}")
    matched = results["explain"].get("pid_matched") or {}
    if len(matched) == 2:
        ratios = [matched[f"{p['frequency_hz']:g}"]["cumulative_error_deg"] / best(p)
                  for p in (slow[0], fast[0])]
        measured += (f"; with the Fig. 6 feed-forward share: {ratios[0]:.3g} and "
                     f"{ratios[1]:.3g}")
    return {"table_i": table_i, "measured": measured}


def conditions_of(c: ServoConditions) -> dict[str, Any]:
    """The conditions as the JSON and the report show them."""
    return {key: (list(value) if isinstance(value, tuple) else value)
            for key, value in vars(c).items()}
