"""The servo run's topics: what each message of ``/drive/command``, ``/drive/feedback``,
``/drive/stop`` and ``/mpc/prediction`` holds, as JSON Schemas (recorded as CDR:
:mod:`hil.core.recording.cdr`). A controller that returns a position or a velocity (a drive
in CSP, CSV, PV) records its set point on ``/drive/command`` beside the fields of a current
controller's (:func:`command_schema`)."""

from __future__ import annotations

from typing import Any

from hil.controllers.base import CURRENT, POSITION, VELOCITY

COMMAND_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.ServoCommand",
    "description": "One controller tick: reference r(k), error y(k) - r(k) (multi-turn), "
                   "commanded current u(k), controller compute time.",
    "properties": {
        "t_s": {"type": "number", "description": "tick time on the schedule grid [s]"},
        "reference_deg": {"type": "number", "description": "placed where the axis started "
                          "(multi-turn, as the position)"},
        "error_deg": {"type": "number", "x-cdr": "float32"},
        "command_mA": {"type": "number", "x-cdr": "float32",
                       "description": "controller output, before the driver's clamp"},
        "disturbance_mA": {"type": "number", "x-cdr": "float32", "description": "scenario "
                           "disturbance torque injected this tick (0x2003)"},
        "compute_us": {"type": "number", "x-cdr": "float32",
                       "description": "controller step time"},
        "path": {"type": "string", "description": "MPC solver path: unconstrained, qp, "
                 "explicit or fallback"},
    },
}
FEEDBACK_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.DriveFeedback",
    "description": "What the drive reported for tick k (TPDO1 + TPDO2 of the previous SYNC).",
    "properties": {
        "position_deg": {"type": "number", "description": "multi-turn, unwrapped by the master"},
        "velocity_deg_s": {"type": "number", "x-cdr": "float32"},
        "current_mA": {"type": "number", "x-cdr": "float32",
                       "description": "torque actual (0x6077) as current"},
        "command_mA": {"type": "number", "x-cdr": "float32", "description": "current "
                       "commanded on the wire in the cycle that produced this feedback (after "
                       "the driver's clamp)"},
        "statusword": {"type": "integer", "x-cdr": "uint16"},
        "cycle": {"type": "integer", "x-cdr": "uint32"},
        "fresh": {"type": "boolean", "description": "false: the TPDOs were late, values repeat"},
        "rtt_us": {"type": "number", "x-cdr": "float32",
                   "description": "SYNC sent -> both TPDOs received"},
    },
}
STOP_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.DriveStop",
    "description": "What the drive reported in each cycle of its safe stop after the run's "
                   "ticks: quick stop until the axis stands (or the quick-stop time-out), "
                   "then disable voltage.",
    "properties": {name: FEEDBACK_SCHEMA["properties"][name]
                   for name in ("position_deg", "velocity_deg_s", "current_mA", "statusword",
                                "cycle", "fresh")},
}
PREDICTION_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.MpcPrediction",
    "description": "The MPC's predicted inputs u(k+i|k), i = 0..H_u-1 (held after), and outputs "
                   "y(k+i|k), i = 1..H_p, one sample period apart (continuous angle frame).",
    "properties": {
        "t_s": {"type": "number"},
        "u_mA": {"type": "array", "items": {"type": "number", "x-cdr": "float32"}},
        "y_deg": {"type": "array", "items": {"type": "number", "x-cdr": "float32"}},
    },
}
#: the field of /drive/command that holds the set point of a controller of each output
SET_POINT_FIELDS = {POSITION: "set_point_deg", VELOCITY: "set_point_deg_s"}


def command_schema(output: str) -> dict[str, Any]:
    """``/drive/command``'s schema for a controller that returns ``output``: a current's is
    :data:`COMMAND_SCHEMA`; a position's or a velocity's has its set point last
    (:data:`SET_POINT_FIELDS`), ``command_mA`` then NaN (no current is commanded: the drive
    chooses it, ``/drive/feedback:current_mA``)."""
    if output == CURRENT:
        return COMMAND_SCHEMA
    unit = "deg" if output == POSITION else "deg/s"
    return {**COMMAND_SCHEMA, "title": "hil.ServoSetPoint",
            "description": f"One controller tick: reference r(k), error y(k) - r(k) "
                           f"(multi-turn), the {output} set point sent to the drive, which "
                           "closes its own loop, controller compute time.",
            "properties": {**COMMAND_SCHEMA["properties"], SET_POINT_FIELDS[output]: {
                "type": "number", "description": f"the {output} set point sent [{unit}] "
                "(command_mA is NaN: the drive chooses the current)"}}}
