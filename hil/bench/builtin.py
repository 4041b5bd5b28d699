"""The built-in bench controllers, built the way a user's are: registered in the entry-point
group ``hil.controllers`` (``eec``, ``bc``) as factories ``(params, context)``.

* ``eec`` - the energy-efficiency controller (MILP receding horizon) with its Kalman filter;
  ``params`` are ``[eec]`` keys of eec.toml (``hp_s``, ``gamma1``, ``time_limit_s``...), which
  the run has laid over the config's ``[eec]``, under the flags (:mod:`hil.bench.settings`);
* ``bc`` - the hysteresis baseline; ``band`` (default 1, the paper's BC) switches each
  peripheral off at ``q_min + band (q_max - q_min)`` instead of ``q_max``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

from hil.bench.config import EecConfig, EecTable
from hil.bench.control import BenchContext, RecordedEEC
from hil.controllers.bench.bc import BasicController
from hil.controllers.bench.eec_settings import EECSettings
from hil.controllers.bench.models import DeviceModel, MachiningModel, load_linear_model
from hil.controllers.bench.prediction import BenchModels
from hil.controllers.bench.problem import BenchProblem
from hil.errors import ConfigError, UsageError


def eec(params: Mapping[str, Any], context: BenchContext) -> RecordedEEC:
    """The EEC of a run, recording its estimates, plans and fallbacks."""
    from hil.controllers.bench.eec import EEC

    config = context.eec
    problem = context.problem
    settings = eec_settings(config.eec)
    models = load_models(config, problem)
    controller = EEC(models, problem, settings, feedback=config.eec.feedback,
                     kalman=config.kalman)
    return RecordedEEC(controller, context.session, problem, context.log, context.origin)


def bc(params: Mapping[str, Any], context: BenchContext) -> BasicController:
    """The hysteresis baseline (the paper's BC); ``band`` narrows its hysteresis."""
    unknown = sorted(set(params) - {"band"})
    if unknown:
        raise ConfigError(f"controller 'bc' takes only the param band, got {', '.join(unknown)}")
    band = params.get("band", 1.0)
    if isinstance(band, bool) or not isinstance(band, int | float):
        raise ConfigError(f"controller 'bc': band must be a number in (0, 1], got {band!r}")
    return BasicController(context.problem, context.step_s, band=float(band))


def eec_settings(table: EecTable) -> EECSettings:
    """The EEC's settings of its ``[eec]`` table."""
    step = table.step_s
    try:
        return EECSettings(
            hp_steps=round(table.hp_s / step), hs_steps=round(table.hs_s / step),
            step_s=step, gamma1=table.gamma1, gamma2=table.gamma2, gamma3=table.gamma3,
            terminal=table.terminal, limit_va=table.limit_va,
            limit_weight=table.limit_weight, peak_resolution_va=table.peak_resolution_va,
            time_limit_s=table.time_limit_s, mip_rel_gap=table.mip_rel_gap, solver=table.solver,
        )
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def model_path(name: str, eec: EecConfig, key: str) -> str:
    """A model file (the config resolved it from the folder of the file that names it)."""
    if os.path.isfile(name):
        return name
    raise ConfigError(f"{eec.source}: key '{key}': model file {name!r} not found (a relative "
                      "path is read from the folder of the config file that names it)")


def load_models(eec: EecConfig, problem: BenchProblem) -> BenchModels:
    """The EEC's load models from the files ``[models]`` names."""
    machining = load_linear_model(
        model_path(eec.models["machining"], eec, "models.machining"), "machining")
    devices = {}
    for name in problem.peripherals:
        path = model_path(eec.models[name], eec, f"models.{name}")
        devices[name] = DeviceModel.from_linear(load_linear_model(path, name))
    models = BenchModels(MachiningModel.from_linear(machining, problem.sequence), devices)
    dts = {machining.dt, *(d.dt for d in devices.values())}
    if len(dts) != 1:
        raise ConfigError(f"{eec.source}: every model must have the same dt, got {sorted(dts)}")
    return models
