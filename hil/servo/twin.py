"""A servo recording replayed into a twin: the drive emulator with a model file (and the
drive's EDS, if given) in lockstep, given the recorded currents one a tick by
:class:`~hil.controllers.servo.replay.CurrentReplay`, through the same pipeline as any run (the
same cycle period, current limit and reference scenario, so a scenario's disturbance comes
back too). Its response is then set against the recording's (:mod:`hil.core.twin`).

The twin's run keeps no safety limits: it drives an emulator only, and a twin that drifts
away from the machine must be compared to the end, not stopped half way.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil.controllers.base import runs_at
from hil.controllers.servo.replay import CurrentReplay
from hil.core.recording.reader import SessionData
from hil.core.twin import Compared, TwinCheck, check_topic
from hil.errors import UsageError
from hil.servo.options import ServoRunOptions
from hil.servo.run import run_servo

COMMAND, FEEDBACK = "/drive/command", "/drive/feedback"
#: the outputs a twin is checked on: field of /drive/feedback -> unit
OUTPUTS = {"position_deg": "deg", "velocity_deg_s": "deg/s"}


@dataclass(frozen=True)
class ServoRecording:
    """What a twin needs of a single-axis servo session: the currents the controller gave
    (before the driver's clamp, which the twin applies again), the run's drive tables,
    current limit, cycle period and reference scenario, and the recorded outputs."""

    path: str
    currents_ma: np.ndarray
    drive_tables: dict[str, Any]
    current_limit_ma: float
    period_s: float
    reference: str
    outputs: dict[str, np.ndarray]
    t_s: np.ndarray


def read_recording(data: SessionData) -> ServoRecording:
    """The servo recording in ``data``; one line naming what is missing otherwise."""
    kind = data.metadata.get("session", {}).get("kind", "")
    if kind != "servo":
        raise UsageError(f"{data.path}: a {kind or 'unknown'} session, not a servo one: the "
                         "twin check replays a servo run's currents")
    commands, feedback = data.topic(COMMAND), data.topic(FEEDBACK)
    if not commands or not feedback:
        raise UsageError(f"{data.path}: no {COMMAND} and {FEEDBACK} to replay (the twin "
                         "check takes a run of one axis)")
    config = json.loads(data.metadata["config"]["json"])
    drive = json.loads(data.metadata["drive"]["json"])
    tables = config["drive"]
    period_s = tables["master"]["cycle_period_us"] / 1e6
    return ServoRecording(
        path=data.path,
        currents_ma=np.array([m["command_mA"] for _, m in commands], dtype=float),
        drive_tables=tables,
        current_limit_ma=float(drive["current_limit"]["run_mA"]),
        period_s=period_s,
        reference=str(config["servo"]["reference"]),
        outputs={name: np.array([m[name] for _, m in feedback], dtype=float)
                 for name in OUTPUTS},
        t_s=np.arange(len(feedback)) * period_s,
    )


def replay_factory(recording: ServoRecording) -> Any:
    """The controller factory of the twin's run: the recording's currents, at its period."""
    @runs_at((round(recording.period_s * 1e6),))
    def replay(reference: Any, params: Any) -> CurrentReplay:
        return CurrentReplay(recording.currents_ma)
    return replay


def twin_overrides(recording: ServoRecording, model: str | None, eds: str | None
                   ) -> dict[str, Any]:
    """The twin's drive tables over the packaged default: the recording's master (its cycle,
    its current limit as the run applied it, no EDS of the machine's), no safety limits, and
    an emulator that is the model (and the EDS) only."""
    master = {**recording.drive_tables["master"], "eds": "",
              "current_limit_mA": recording.current_limit_ma}
    emulator: dict[str, Any] = {}
    if model is not None:
        emulator["model"] = os.path.abspath(model)
    if eds is not None:
        emulator["eds"] = os.path.abspath(eds)
    return {"master": master, "safety": {"enabled": False}, "emulator": emulator}


def run_twin(recording: ServoRecording, model: str | None, eds: str | None, out: str,
             quiet: bool = False) -> None:
    """The twin's run of the recording's currents, recorded to ``out`` (``quiet``: no
    progress line)."""
    options = ServoRunOptions(
        controller=replay_factory(recording), drive="emulated", out=out, quiet=quiet,
        reference=recording.reference,
        duration_s=recording.currents_ma.size * recording.period_s,
        drive_overrides=twin_overrides(recording, model, eds))
    run_servo(options)


def check_twin(recording: ServoRecording, twin: SessionData, min_fit_pct: float
               ) -> tuple[TwinCheck, list[Compared]]:
    """The twin's position and velocity against the recording's."""
    return check_topic(recording.outputs, OUTPUTS, twin, FEEDBACK, min_fit_pct)
