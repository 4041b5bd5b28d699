"""The sweeps that explain the servo paper's differences, each with where the paper's figure
falls on it (:func:`explain`).
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise
from typing import Any

from hil.paper.servo_conditions import ServoConditions
from hil.paper.servo_measures import push_response, tracking
from hil.paper.servo_runs import Session

#: the paper's figures quoted in its text (section III-B)
PAPER_FIG5 = {"max_error_deg": 0.0643, "max_error_pct": 3.2}
PAPER_FIG6 = {"max_error_deg": 0.5021, "max_error_pct": 25.1}


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
