"""The servo session's panels in the HTML report (entry point ``hil.html_panels``), as the
PNG of ``hil report --out`` draws them: position against the reference, the tracking error and
the commanded and measured current with the current limit; with several axes, each axis'
error and current and the contour error of a path. (The MPC's prediction waterfall and the
X-Y view of a path are in the PNG only.)"""

from __future__ import annotations

import numpy as np

from hil.core.html_report.panels import Panel, Trace
from hil.core.recording.reader import SessionData
from hil.servo.report import axis_names, current_limit


def servo_panels(data: SessionData, origin_ns: int) -> list[Panel]:
    """Tracking, error and current of a single axis; per axis for several."""
    names = axis_names(data)
    if names:
        return _axes_panels(data, names, origin_ns)
    command = data.arrays("/drive/command")
    if command["log_time_ns"].size == 0 or "error_deg" not in command:
        return []
    t = (command["log_time_ns"] - origin_ns) / 1e9
    reference, error = command["reference_deg"], command["error_deg"]
    feedback = data.arrays("/drive/feedback")
    current = [Trace("commanded", t, command["command_mA"])]
    if "current_mA" in feedback:
        current.append(Trace("drive (torque actual)", (feedback["log_time_ns"] - origin_ns) / 1e9,
                             feedback["current_mA"]))
    limit = current_limit(data)
    lines = ((limit, f"current limit {limit:g} mA"), (-limit, "")) if limit else ()
    return [
        Panel("tracking", "angle [deg]", (Trace("reference", t, reference, dash=True),
                                          Trace("position", t, reference + error))),
        Panel("tracking error (position - reference)", "error [deg]",
              (Trace("error", t, error),)),
        Panel("motor current", "current [mA]", tuple(current), lines),
    ]


def _axes_panels(data: SessionData, names: list[str], origin_ns: int) -> list[Panel]:
    errors, currents = [], []
    for name in names:
        command = data.arrays(f"/axis/{name}/command")
        t = (command["log_time_ns"] - origin_ns) / 1e9
        if "error_deg" in command:
            errors.append(Trace(f"axis {name}", t, command["error_deg"]))
        if "command_mA" in command:
            currents.append(Trace(f"axis {name}", t, command["command_mA"]))
    panels = [Panel("tracking error per axis (position - reference)", "error [deg]",
                    tuple(errors)),
              Panel("commanded current per axis", "current [mA]", tuple(currents))]
    contour = data.arrays("/path/contour")
    if "contour_error_deg" in contour:
        panels.append(Panel("contour error of the path", "error [deg]", (Trace(
            "contour error", (contour["log_time_ns"] - origin_ns) / 1e9,
            np.asarray(contour["contour_error_deg"], float)),)))
    return panels
