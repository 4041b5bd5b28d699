"""What the servo paper's tables read from a session: its tracking KPIs, how the MPC's
recorded predictions compare with the currents applied, the explicit MPC's controllers, and
how the axis answered a push.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hil.core.recording.reader import read_session
from hil.paper.servo_runs import CONTROLLER_TOPIC, Session

KPI_KEYS = ("max_error_deg", "max_error_pct", "rms_error_deg", "cumulative_error_deg",
            "peak_current_mA", "peak_requested_mA")


def tracking(session: Session) -> dict[str, Any]:
    """The KPIs the tables quote of one session."""
    row = {key: session[key] for key in KPI_KEYS}
    row["step_us"] = session["step_us"]
    return row


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


def controllers_used(mcap: str, start_s: float = 0.0, end_s: float = math.inf) -> list[int]:
    """The explicit MPC's controllers (paper numbering) over ticks in [start_s, end_s)."""
    used = read_session(mcap).arrays(CONTROLLER_TOPIC)
    window = (used["t_s"] >= start_s - 1e-9) & (used["t_s"] < end_s - 1e-9)
    return sorted({int(v) for v in used["controller"][window]})


def share_in(mcap: str, controller: int) -> float:
    used = read_session(mcap).arrays(CONTROLLER_TOPIC)["controller"]
    return float(np.mean(used == controller))


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
