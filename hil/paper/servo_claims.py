"""What the servo paper says of its results, held against hil's measurements: each statement
with where it is made, whether hil's sessions bear it out, and the figures that decide it.
"""

from __future__ import annotations

import math
from itertools import pairwise
from typing import Any

from hil.paper.servo_conditions import ServoConditions


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
