"""A bench session re-simulated with another controller (``hil resim``): the recorded run's
configuration rebuilt as a bench run of its own, in lockstep on hil's bench emulator, through
the pipeline of any bench run (:class:`~hil.bench.run.BenchExperiment`).

Kept from the recording: its bench and controller tables as they ran (relays and their dwell,
sampling, safety limits, the machining sequence, the plant and its noise seed, the disturbance,
the emulator's ``[faults]`` schedule, the decision step and horizons), the number of cycles and
the limits. Replaced: the controller and its parameters, and each load ``--model LOAD=F.json``
names by that model file. A recording of hardware is re-simulated against the emulator its
recorded ``[plant]`` describes (the packaged one's unless configured).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from hil.bench.openers import is_emulated
from hil.bench.options import BenchRunOptions
from hil.bench.run import BenchExperiment
from hil.bench.twin import parse_models
from hil.core.resim import Recorded, resim_metadata, resolved_paths, write_config
from hil.core.run import RunResult, run_experiment
from hil.core.session import Session
from hil.errors import UsageError

KINDS = ("bench",)
EMULATED = "emulated"


@dataclass(frozen=True)
class BenchResim:
    """A bench resimulation, decided: the run's options (its config a file in a folder the
    caller owns), the recorded bench's URL and what the emulator stands for."""

    options: BenchRunOptions
    recorded_url: str
    plant: str

    @property
    def of_hardware(self) -> bool:
        return not is_emulated(self.recorded_url)


def plan_resim(recorded: Recorded, controller: str | None, params: Mapping[str, Any],
               models: Sequence[str], out: str, folder: str, quiet: bool = False
               ) -> BenchResim:
    """The resimulation of ``recorded`` with ``controller`` (None: the recorded one) and
    ``params`` (laid over the recorded ones when the controller is the recorded one), each
    ``LOAD=F.json`` of ``models`` that load's model, recorded to ``out``; its config is
    written into ``folder``. ``quiet``: no progress line."""
    run = recorded.table("run")
    bench, controllers = recorded.table("bench"), recorded.table("controllers")
    url = str(run.get("bench") or (bench.get("bus") or {}).get("url", EMULATED))
    same = controller is None or controller == run.get("controller")
    spec = str(run.get("controller", "")) if controller is None else controller
    laid = {**(run.get("params") or {}), **params} if same else dict(params)
    tables = resolved_paths({**bench, **controllers}, recorded.settings)
    for table in ("controller", "limits"):  # the recorded run's, given as options below
        tables.pop(table, None)
    loads = list((tables.get("plant") or {}).get("loads") or {})
    for name, path in parse_models(models, loads).items():
        tables["plant"]["loads"][name]["model"] = path
    try:
        options = BenchRunOptions(
            controller=spec, params=laid, bench=EMULATED, cycles=int(run["cycles"]),
            duration_s=run.get("duration_s"), out=out,
            config_path=write_config(tables, folder, "bench.toml"),
            limits=recorded.limits(run), controller_budget_s=run.get("controller_budget_s"),
            quiet=quiet)
    except KeyError as exc:
        raise UsageError(f"{recorded.path}: its recorded bench run has no {exc.args[0]!r} (a "
                         "session of an older hil?): it cannot be re-simulated") from None
    plant = ("the emulator with the load models " + ", ".join(models) if models else
             "hil's emulator built from the recorded config" if not is_emulated(url) else
             "the recorded emulator")
    return BenchResim(options, url, plant)


class ResimExperiment(BenchExperiment):
    """A bench run that records which session it re-simulates (metadata ``resim``)."""

    def __init__(self, resim: BenchResim, recorded: str) -> None:
        super().__init__(resim.options)
        self.resim, self.recorded = resim, recorded

    def start(self, session: Session) -> None:
        super().start(session)
        session.recorder.metadata("resim", resim_metadata(
            self.recorded, self.planned.label, self.planned.params, self.resim.plant))


def run_resim(resim: BenchResim, recorded: str) -> RunResult:
    """The resimulation's run, recorded to its ``out``."""
    return run_experiment(ResimExperiment(resim, recorded))
