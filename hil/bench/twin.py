"""A bench recording replayed into a twin: the bench emulator with the recorded run's config
tables (sampling, relays, sequence, safety, plant and its noise seed), its loads replaced by the
model files ``--model LOAD=F.json`` names, in lockstep through the run pipeline of any bench
run (:class:`~hil.bench.run.BenchExperiment`, so the safety layer and its dwell act as in any
run). Every relay is switched at the tick it was recorded switching (``/bench/relays``): the
peripherals by :class:`~hil.controllers.bench.replay.RelayReplay` deciding every tick, the
machining relays by the sequence player playing the recorded states rather than the
sequence table. The twin's ``/bench/power`` is then set against the recording's
(:mod:`hil.core.twin`).

The machining relays are replayed as recorded, not played from the table again: one path for
``hil bench run`` sessions (where the two agree) and for ``hil bench identify`` sessions of every
``--machining`` mode (off, the sequence, or PRBS on M1/M2).
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import tomli_w

from hil.bench.options import BenchRunOptions
from hil.bench.run import BenchExperiment, BenchPlan
from hil.bench.sequence import SequenceSchedule
from hil.controllers.bench.problem import MachiningSequence
from hil.controllers.bench.replay import RelayReplay
from hil.core.recording.reader import SessionData
from hil.core.run import run_experiment
from hil.core.session import Session
from hil.core.twin import Compared, TwinCheck, check_topic
from hil.errors import UsageError

POWER, RELAYS = "/bench/power", "/bench/relays"
#: the session kinds a bench twin replays
KINDS = ("bench", "bench-identify")


@dataclass(frozen=True)
class BenchRecording:
    """What a twin needs of a bench session: its bench config tables, the relays' states
    written at each tick, the sampling period and the recorded ``/bench/power`` outputs."""

    path: str
    tables: dict[str, Any]
    written: dict[str, np.ndarray]   # relay -> 0/1 written at tick k (held from tick k + 1)
    period_s: float
    outputs: dict[str, np.ndarray]   # total_va and the loaded phases' va_lN [VA]
    t_s: np.ndarray

    @property
    def loads(self) -> list[str]:
        return list(self.tables["plant"]["loads"])

    @property
    def ticks(self) -> int:
        return self.t_s.size


def is_bench_session(data: SessionData) -> bool:
    return data.metadata.get("session", {}).get("kind", "") in KINDS


def compared_fields(tables: Mapping[str, Any]) -> list[str]:
    """``total_va`` and the apparent power of every phase a load (or the base) is on."""
    plant = tables["plant"]
    phases = {*plant["base"].get("phases", ()),
              *(p for load in plant["loads"].values() for p in load.get("phases", ()))}
    return ["total_va", *(f"va_{p.lower()}" for p in sorted(phases))]


def read_recording(data: SessionData) -> BenchRecording:
    """The bench recording in ``data``; one line naming what is missing otherwise."""
    relays, power = data.topic(RELAYS), data.topic(POWER)
    if len(relays) < 2 or not power:
        raise UsageError(f"{data.path}: no {RELAYS} and {POWER} to replay (the session "
                         "recorded no samples)")
    tables = json.loads(data.metadata["config"]["json"])["bench"]
    names = list(tables["relays"])
    # /bench/relays holds the states read at tick k: those written at tick k - 1
    states = {n: np.array([m[n] for _, m in relays], dtype=np.int8) for n in names}
    written = {n: np.append(s[1:], s[-1]) for n, s in states.items()}
    fields = [f for f in compared_fields(tables) if f in power[0][1]]
    period_s = float(tables["sampling"]["period_s"])
    return BenchRecording(
        path=data.path, tables=tables, written=written, period_s=period_s,
        outputs={f: np.array([m[f] for _, m in power], dtype=float) for f in fields},
        t_s=np.arange(len(relays)) * period_s)


def parse_models(specs: Sequence[str], loads: Sequence[str]) -> dict[str, str]:
    """``["P1=p1.json", ...]`` -> ``{"P1": "/abs/p1.json"}``; UsageError on a malformed one,
    an unknown load or a missing file."""
    models: dict[str, str] = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            raise UsageError(f"--model {spec}: a bench twin's model is LOAD=F.json, a load of "
                             f"[plant.loads] ({', '.join(loads)}), e.g. --model P1=P1.json")
        if name not in loads:
            raise UsageError(f"--model {spec}: {name!r} is not a load of the recorded bench "
                             f"(loads: {', '.join(loads)})")
        if name in models:
            raise UsageError(f"--model {spec}: load {name} is given a model twice")
        if not os.path.isfile(path):
            raise UsageError(f"--model {spec}: no such file {path}")
        models[name] = os.path.abspath(path)
    return models


def twin_tables(recording: BenchRecording, models: Mapping[str, str]) -> dict[str, Any]:
    """The recording's bench tables with each named load's model file in place of its own."""
    tables = json.loads(json.dumps(recording.tables))
    for name, path in models.items():
        tables["plant"]["loads"][name]["model"] = path
    return tables


class RecordedMachining(SequenceSchedule):
    """The machining relays' states as recorded, for the sequence player: at ``t_ns`` after
    its first tick, the states written at that tick."""

    def __init__(self, sequence: MachiningSequence, replay: RelayReplay, period_s: float
                 ) -> None:
        super().__init__(sequence)
        self.replay = replay
        self.relays = list(replay.states)
        self._tick_ns = round(period_s * 1e9)

    def states_at(self, t_ns: int) -> dict[str, bool]:
        return self.replay.at(round(t_ns / self._tick_ns))


class TwinExperiment(BenchExperiment):
    """A bench run replaying ``recording``: as long as the recording, its machining relays
    played as recorded."""

    def __init__(self, opts: BenchRunOptions, recording: BenchRecording) -> None:
        super().__init__(opts)
        self.recording = recording

    def plan(self) -> BenchPlan:
        return replace(super().plan(), duration_s=self.recording.ticks * self.recording.period_s)

    def start(self, session: Session) -> None:
        super().start(session)
        rig = self.state.rig
        assert rig is not None and rig.player is not None  # a run plays the sequence
        machining = rig.config.problem.sequence
        replay = RelayReplay({n: self.recording.written[n] for n in machining.relays},
                             self.recording.period_s)
        rig.player.sequence = RecordedMachining(machining, replay, self.recording.period_s)


def replay_factory(recording: BenchRecording, peripherals: Sequence[str]) -> Any:
    """The controller factory of the twin's run: the peripherals' recorded states."""
    def replay(params: Mapping[str, Any]) -> RelayReplay:
        return RelayReplay({n: recording.written[n] for n in peripherals}, recording.period_s)
    return replay


def run_twin(recording: BenchRecording, models: Mapping[str, str], out: str,
             quiet: bool = False) -> None:
    """The twin's run of the recording's relays, recorded to ``out``: lockstep on the bench
    emulator, a decision every sampling period (``[eec] step_s``) so every switch lands on
    its tick (``quiet``: no progress line)."""
    from hil.bench.config import parse_bench_config

    tables = twin_tables(recording, models)
    # a model file that does not fit the bench is refused here, naming the recording
    peripherals = parse_bench_config(tables, f"{recording.path} with --model"
                                     ).problem.peripherals
    with tempfile.TemporaryDirectory(prefix="hil-twin-") as folder:
        config = os.path.join(folder, "twin.toml")
        with open(config, "wb") as file:
            file.write(tomli_w.dumps(tables).encode())
        options = BenchRunOptions(
            controller=replay_factory(recording, peripherals), bench="emulated", cycles=1,
            out=out, quiet=quiet, config_path=config,
            overrides={"step_s": recording.period_s})
        run_experiment(TwinExperiment(options, recording))


def check_twin(recording: BenchRecording, twin: SessionData, min_fit_pct: float
               ) -> tuple[TwinCheck, list[Compared]]:
    """The twin's ``/bench/power`` against the recording's."""
    return check_topic(recording.outputs, dict.fromkeys(recording.outputs, "VA"), twin, POWER,
                       min_fit_pct)
