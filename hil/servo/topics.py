"""The servo run's topics: what each message of ``/drive/command``, ``/drive/feedback`` and
``/mpc/prediction`` holds, as JSON Schemas (recorded as CDR: :mod:`hil.core.cdr`)."""

from __future__ import annotations

from typing import Any

COMMAND_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.ServoCommand",
    "description": "One controller tick: reference r(k), error y(k) - r(k) (wrapped to ±180 "
                   "deg), commanded current u(k), controller compute time.",
    "properties": {
        "t_s": {"type": "number", "description": "tick time on the schedule grid [s]"},
        "reference_deg": {"type": "number"},
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
