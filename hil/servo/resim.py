"""A servo session re-simulated with another controller (``hil resim``): the recorded run's
configuration rebuilt as a servo run of its own, in lockstep on hil's drive emulator, through
the pipeline of any run (:func:`hil.servo.run.run_servo`'s :class:`ServoExperiment`).

Kept from the recording: the drive tables as they ran (cycle period, current limit, safety
limits, the emulator's axis, friction, disturbance and fault schedule), the axes, the reference
scenario (and its disturbance), the duration, the MPC horizons, the settle time, the prediction
rate and the limits. Replaced: the controller and its parameters, and, with a model file, the
emulator's axis (``[emulator] model``). A recording of hardware is re-simulated against the
emulator its recorded ``[emulator]`` table describes (the packaged one's unless configured),
without the machine's EDS, its current limit the one the drive applied.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from hil.core.registry import scheme_of
from hil.core.resim import Recorded, resim_metadata, resolved_paths, write_config
from hil.core.run import RunResult, run_experiment
from hil.core.session import Session
from hil.errors import UsageError
from hil.servo.config import EMULATED
from hil.servo.options import ServoRunOptions
from hil.servo.run import ServoExperiment
from hil.servo.settings import emulated_url

KINDS = ("servo",)


@dataclass(frozen=True)
class ServoResim:
    """A servo resimulation, decided: the run's options (its drive config a file in a folder the
    caller owns), the recorded drive's URL and what the emulator stands for."""

    options: ServoRunOptions
    recorded_url: str
    plant: str          # what the emulator is: "the recorded emulator", "..."

    @property
    def of_hardware(self) -> bool:
        return scheme_of(self.recorded_url) != EMULATED


def recorded_url(run: Mapping[str, Any], tables: Mapping[str, Any]) -> str:
    """The URL of the drive the recorded run drove: its ``--drive``, else its ``[bus]``
    (``url``, else ``interface`` and ``channel``)."""
    url, _ = emulated_url(run.get("drive"))
    if url:
        return url
    bus = tables.get("bus") or {}
    if bus.get("url"):
        return str(bus["url"])
    interface = str(bus.get("interface", EMULATED))
    return EMULATED if interface == EMULATED else f"{interface}://{bus.get('channel', '')}"


def plan_resim(recorded: Recorded, controller: str | None, params: Mapping[str, Any],
               model: str | None, out: str, folder: str,
               drive_info: Mapping[str, Any] | None = None, quiet: bool = False
               ) -> ServoResim:
    """The resimulation of ``recorded`` with ``controller`` (None: the recorded one) and
    ``params`` (laid over the recorded ones when the controller is the recorded one),
    ``model`` the emulator's axis (None: the recorded emulator's), recorded to ``out``; its
    drive config is written into ``folder``. ``drive_info``: the session's ``drive``
    metadata (the current limit the drive applied). ``quiet``: no progress line."""
    run, tables = recorded.table("servo"), recorded.table("drive")
    if not isinstance(tables.get("master"), Mapping):
        raise UsageError(f"{recorded.path}: its recorded drive config has no [master] table: it "
                         "cannot be re-simulated")
    url = recorded_url(run, tables)
    hardware = scheme_of(url) != EMULATED
    same = controller is None or controller == run.get("controller")
    spec = str(run.get("controller", "")) if controller is None else controller
    laid = {**(run.get("params") or {}), **params} if same else dict(params)
    tables = resolved_paths(tables, recorded.settings)
    for table in ("controller", "limits"):  # the recorded run's, given as options below
        tables.pop(table, None)
    for axis in tables.get("axis", []):
        axis["bus"] = ""                     # every axis on the emulated bus
    if hardware:
        tables["master"]["eds"] = ""         # the emulator is no twin of the machine's EDS
        applied = ((drive_info or {}).get("current_limit") or {}).get("run_mA")
        if isinstance(applied, (int, float)):
            tables["master"]["current_limit_mA"] = min(
                float(tables["master"]["current_limit_mA"]), float(applied))
    if model is not None:
        if not os.path.isfile(model):
            raise UsageError(f"--model {model}: no such file")
        tables.setdefault("emulator", {})["model"] = os.path.abspath(model)
    axes = recorded_axes(run, tables)
    try:
        options = ServoRunOptions(
            controller=spec, params=laid, drive=EMULATED,
            ert=run["ert"], ht=run["ht"], hu=run["hu"], hp=run["hp"],
            reference=run["reference"], duration_s=run["duration_s"], out=out,
            drive_config=write_config(tables, folder, "drive.toml"),
            settle_s=run["settle_s"], prediction_every=_prediction_every(run),
            limits=recorded.limits(run), controller_budget_s=run.get("controller_budget_s"),
            quiet=quiet, axes=axes,
            from_here=bool(run.get("from_here")))
    except KeyError as exc:
        raise UsageError(f"{recorded.path}: its recorded servo run has no {exc.args[0]!r} (a "
                         "session of an older hil?): it cannot be re-simulated") from None
    plant = ("the emulator with the axis model " + os.path.basename(model) if model else
             "hil's emulator built from the recorded config" if hardware else
             "the recorded emulator")
    return ServoResim(options, url, plant)


def recorded_axes(run: Mapping[str, Any], tables: Mapping[str, Any]) -> str | None:
    """The recorded run's ``--axes`` (``NAME=NODE,...``, every axis on the emulated bus): None
    when it named none or its config's ``[[axis]]`` tables did (they come with the tables)."""
    axes = run.get("axes")
    if tables.get("axis") or not isinstance(axes, list):
        return None
    return ",".join(f"{axis['name']}={axis['node']}" for axis in axes)


def _prediction_every(run: Mapping[str, Any]) -> int:
    """The prediction rate the recorded run had (every tick in lockstep unless long, ...)."""
    given = run.get("prediction_every")
    recorded = ServoRunOptions(controller="", duration_s=float(run["duration_s"]),
                               realtime=bool(run.get("realtime")),
                               prediction_every=given if isinstance(given, int) else None)
    return recorded.prediction_period


class ResimExperiment(ServoExperiment):
    """A servo run that records which session it re-simulates (metadata ``resim``)."""

    def __init__(self, resim: ServoResim, recorded: str) -> None:
        super().__init__(resim.options)
        self.resim, self.recorded = resim, recorded

    def start(self, session: Session) -> None:
        super().start(session)
        options = self.resim.options
        session.recorder.metadata("resim", resim_metadata(
            self.recorded, options.label, self.planned.params, self.resim.plant))


def run_resim(resim: ServoResim, recorded: str) -> RunResult:
    """The resimulation's run, recorded to its ``out``."""
    return run_experiment(ResimExperiment(resim, recorded))
