"""Identifying a servo axis: the experiment ``hil servo identify`` runs, and the signals
``hil identify --servo`` reads from its session.

The experiment is an ordinary servo run (same pipeline, safety monitor, current clamp, safe stop
and recording as ``hil servo run``) whose controller is
:class:`~hil.controllers.servo.excitation.Excitation` (:func:`excitation`, spec
:data:`CONTROLLER`) with the reference held where the axis starts (:data:`HOLD_HERE`, from
here): the stabiliser keeps the axis there, and the safety net's following error is the
distance from it.

The signals: input, the current commanded on the wire (``/drive/feedback``'s ``command_mA``,
after the clamp); output, the multi-turn position (``position_deg``). Feedback k is what the
drive reported from the SYNC of tick k-1, and carries the command of that cycle, u(k-1), next
to y(k). :func:`servo_signals` pairs y(k) with u(k), the next message's command (the current
applied from y(k) on), so that the model reads as the published one, x(k+1) = A x(k) + B u(k),
y(k) = C x(k), without feedthrough (D = 0). The command is taken as the drive applies it: rounded
to its torque object's unit (a per mille of the rated current, :func:`torque_unit_ma`): on a
double integrator the half-unit errors of the unrounded command add up to a drift that costs
the held-out fit a few percent.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import numpy as np

from hil.controllers.base import runs_at
from hil.controllers.errors import ControllerSetupError
from hil.controllers.servo.excitation import Excitation, ExcitationConfig, check_fits
from hil.controllers.servo.excitation_defaults import (
    DEFAULT_AMPLITUDE_MA,
    DEFAULT_DURATION_S,
    DEFAULT_KD_MA_PER_DEG_S,
    DEFAULT_KIND,
    DEFAULT_KP_MA_PER_DEG,
    DEFAULT_SEED,
    KINDS,
)
from hil.controllers.servo.model import MODEL_PERIODS_US
from hil.controllers.servo.references import Reference
from hil.core.config import Table
from hil.core.identify import aligned_signals, parse_signal
from hil.core.recording.reader import SessionData
from hil.core.settings import LooseningRefusedError, Setting
from hil.errors import UsageError
from hil.servo.options import ServoRunOptions
from hil.servo.settings import ServoSettings, resolve_servo

#: the experiment's controller, as a run records it
CONTROLLER = "hil.servo.identify:excitation"
#: the experiment's reference: held where the axis starts
HOLD_HERE = "hold:position=0"
#: ``hil servo identify``'s flags (argparse dests) -> the controller's params
PARAM_FLAGS = {"amplitude": "amplitude", "excitation": "kind", "seed": "seed"}


@runs_at(MODEL_PERIODS_US)
def excitation(reference: Reference, params: Mapping[str, Any], context: Any) -> Excitation:
    """The experiment's controller: params ``amplitude`` [mA], ``kind`` (prbs, multisine,
    chirp), ``seed``, ``kp`` [mA/deg], ``kd`` [mA per deg/s]; its peak must fit inside the
    run's current bound (``context.umax``)."""
    table = Table(params, "controller 'excitation' params")
    config = ExcitationConfig(
        amplitude_ma=table.number("amplitude", DEFAULT_AMPLITUDE_MA, above=0),
        kind=table.string("kind", DEFAULT_KIND, choices=KINDS),
        seed=table.integer("seed", DEFAULT_SEED, at_least=1),
        kp=table.number("kp", DEFAULT_KP_MA_PER_DEG, above=0),
        kd=table.number("kd", DEFAULT_KD_MA_PER_DEG_S, at_least=0))
    table.done()
    return Excitation(reference, config, context.umax, context.period_s)


def identify_options(flags: Mapping[str, Any], *, need_controller: bool = True
                     ) -> ServoRunOptions:
    """The servo run of ``hil servo identify``'s flags (argparse dests): the excitation
    controller, its params (``--param`` laid under the experiment's flags), the reference held
    from here. An amplitude that cannot fit inside the run's current limit with the
    stabiliser's share is a UsageError in one line (checked before anything is opened; the
    drive's own lower limit, read when it is opened, is checked by the controller)."""
    params = dict(flags.get("param") or [])
    params |= {key: flags[flag] for flag, key in PARAM_FLAGS.items()
               if flags.get(flag) is not None}
    run_flags = {**flags, "controller": CONTROLLER, "param": list(params.items()),
                 "reference": HOLD_HERE, "from_here": True,
                 "duration": flags.get("duration") or DEFAULT_DURATION_S}
    options = ServoRunOptions.from_flags(run_flags, need_controller=need_controller)
    if need_controller:
        settings = resolve_identify(options)
        mode = settings.drive.master.mode
        if mode != "cst":
            raise UsageError(f"hil servo identify excites the axis with currents, in CST: "
                             f"[master] mode = {mode!r} sends the drive other set points; "
                             "give it a config with mode = \"cst\"")
        amplitude = {**settings.drive.run.params, **params}.get("amplitude",
                                                                 DEFAULT_AMPLITUDE_MA)
        try:
            check_fits(float(amplitude), settings.umax_ma, "--amplitude")
        except ControllerSetupError as exc:
            raise UsageError(str(exc)) from None
        except (TypeError, ValueError):
            pass  # not a number: the controller's params name it
    return options


def resolve_identify(options: ServoRunOptions) -> ServoSettings:
    """:func:`~hil.servo.settings.resolve_servo` for the experiment, which offers no flag to
    loosen a limit: a refusal says so, without naming ``hil servo run``'s."""
    try:
        return resolve_servo(options)
    except LooseningRefusedError as exc:
        raise UsageError(exc.without_hatch) from None


def identify_settings(options: ServoRunOptions, flags: Mapping[str, Any]) -> list[Setting]:
    """``--print-config``: the run's settings, what the experiment sets itself said so (origin
    ``hil servo identify``), its params' origin the flags that set them."""
    own = "hil servo identify"
    given = [f"--{flag}" for flag in (*PARAM_FLAGS, "param") if flags.get(flag)]
    origins = {"run.controller": own, "run.reference": own, "run.from_here": own}
    if flags.get("duration") is None:
        origins["run.duration_s"] = own
    settings = resolve_identify(options).settings()
    return [replace(s, origin=origins[s.key]) if s.key in origins else
            replace(s, origin=", ".join(given)) if s.key == "run.params" and
            s.origin == "--param" else s for s in settings]


def feedback_topic(axis: str | None) -> str:
    """The feedback topic of the run's one axis (None) or of axis ``axis``."""
    return "/drive/feedback" if axis is None else f"/axis/{axis}/feedback"


def servo_signals(data: SessionData, axis: str | None = None
                  ) -> tuple[str, str, np.ndarray, np.ndarray, float, int, int]:
    """(input name, output name, u, y, dt, irregular intervals, stale samples) of a servo
    session: y(k) the position of feedback k, u(k) the command of feedback k+1 (see the
    module). A session without the topic is a UsageError naming the topics it has."""
    topic = feedback_topic(axis)
    if not data.topic(topic):
        feedbacks = sorted(t for t in data.messages if t.endswith("/feedback")
                           and data.messages[t])
        hint = ("; its feedback topics: " + ", ".join(feedbacks) + " (pick one with --axis "
                "NAME)") if feedbacks else "; is it a servo session?"
        raise UsageError(f"--servo: the session has no messages on {topic}{hint}")
    source, target = f"{topic}:command_mA", f"{topic}:position_deg"
    u, y, dt, irregular = aligned_signals(data, [parse_signal(source)], [parse_signal(target)])
    if len(y) < 3:
        raise UsageError(f"--servo: {topic} holds fewer than 3 samples; nothing to identify")
    stale = sum(1 for _, message in data.topic(topic) if not message.get("fresh", True))
    unit = torque_unit_ma(data, axis)
    if unit is not None:
        u = np.round(u / unit) * unit
    return source, target, u[1:], y[:-1], dt, irregular, stale


def torque_unit_ma(data: SessionData, axis: str | None) -> float | None:
    """The current one unit of the torque object stands for [mA] (a per mille of the drive's
    rated current, from the session's ``drive`` metadata): the drive applies the command
    rounded to it. None when the session does not say."""
    try:
        described = json.loads(data.metadata.get("drive", {}).get("json", ""))
        if axis is not None:
            described = described[axis]
        rated = float(described["scaling"]["rated_current_ma"])
    except (ValueError, KeyError, TypeError):
        return None
    return rated / 1000.0 if rated > 0 else None
