"""``hil bench identify``: a PRBS relay-switching experiment recorded for ``hil identify``.

Loop (base period = the bench's sampling period, tasks in this order every tick):

1. [lockstep emulator] plant step, 2. sampler (meter, levels, safety service; publishes
   ``/bench/power``, ``/bench/levels``, ``/bench/relays``), 3. [machining sequence player] -
   all from :func:`~hil.bench.rig.attach_rig`, the bench opened first as a run opens it
   (lockstep over the wire where hil's emulator answers at ``--bench URL``);
4. ``prbs``: switches every chosen relay with its own seeded pseudo-random binary sequence
   and publishes ``/ident/relays``.

PRBS: the time of each relay is cut into bits of ``min_hold`` (default the relay's dwell,
never shorter); at every bit boundary the relay keeps or changes its state with probability
1/2 (independent seeded streams per relay), so every hold lasts a whole number of bits. A
switch is only written once the safety layer's dwell is over (compared exactly as the layer
does), so a well-formed experiment has no deferred request; deferrals are counted anyway.

``/ident/relays`` holds, for every relay of the experiment (PRBS and sequence alike), the
state *written at this tick* (``P1``) and the switch-on event (``P1_start``, 1 at the tick the
relay was switched on). The plant latches a write for its next step, so the meter reading
logged at the same tick does not yet see it: models from these inputs have D = 0
(``--no-feedthrough``), the convention of :mod:`hil.controllers.bench.models`.
"""

from __future__ import annotations

import math
import os
import shlex
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from hil.bench.identify_options import MACHINING_MODES, IdentifyOptions
from hil.bench.openers import open_bench_device, planned_clock
from hil.bench.rig import BenchRig, attach_rig
from hil.core.loop import Task
from hil.core.run import EventBuffer, default_session_path
from hil.core.session import Session
from hil.errors import UsageError

if TYPE_CHECKING:
    from hil.bench.config import BenchConfig

TOPIC = "/ident/relays"


@dataclass
class PrbsRelay:
    """One relay's PRBS: bit length in samples, its own random stream, its state."""

    name: str
    bit_samples: int
    dwell_s: float
    rng: np.random.Generator
    state: bool = False
    last_switch_ns: int | None = None
    next_bit: int = 0  # sample index of the next bit boundary
    switches: int = 0


@dataclass
class ExperimentLog:
    """What the experiment did, for the summary."""

    switches: dict[str, int] = field(default_factory=dict)
    late_ticks: int = 0  # ticks a switch waited so the safety layer's dwell is surely over
    deferred: int = 0  # requests the safety layer deferred (0 in a well-formed run)
    failed: int = 0


class PrbsTask(Task):
    """Switches the PRBS relays and records every experiment relay as written this tick."""

    def __init__(self, rig: BenchRig, prbs: list[PrbsRelay], recorded: list[str], session: Session,
                 log: ExperimentLog, progress: Callable[[int], None], divisor: int) -> None:
        super().__init__("prbs", divisor)
        self.rig, self.prbs, self.recorded, self.log = rig, prbs, recorded, log
        self._progress = progress
        self._sample = 0
        self._changes: dict[str, bool] = {}
        self._previous = {name: False for name in recorded}
        self._topic = session.topic(TOPIC, {
            "type": "object", "title": "hil.IdentRelays",
            "description": "Relays of the identification experiment as written at this tick "
                           "(the plant acts on them from its next step) and their switch-on "
                           "events (NAME_start = 1 at the tick the relay was switched on)",
            "properties": {f: {"type": "integer", "enum": [0, 1]}
                           for name in recorded for f in (name, f"{name}_start")},
        })

    def compute(self, t_ns: int) -> None:
        """The PRBS bits of this sample, and the relays whose dwell lets them switch now."""
        sample = self._sample
        self._sample += 1
        changes: dict[str, bool] = {}
        for relay in self.prbs:
            if sample >= relay.next_bit:
                relay.next_bit += relay.bit_samples
                relay.state = bool(relay.rng.integers(2))
            if relay.state != self.rig.bench.commanded()[relay.name]:
                if self._dwell_over(relay, t_ns):
                    changes[relay.name] = relay.state
                else:
                    self.log.late_ticks += 1
        self._changes = changes

    @staticmethod
    def _dwell_over(relay: PrbsRelay, t_ns: int) -> bool:
        """The safety layer's own test (float seconds), so a switch it would defer waits."""
        if relay.last_switch_ns is None:
            return True
        return t_ns / 1e9 >= relay.last_switch_ns / 1e9 + relay.dwell_s

    def write(self, t_ns: int) -> None:
        bench, changes = self.rig.bench, self._changes
        if changes and bench.link_up:
            for name, outcome in bench.set_relays(changes, t_ns).items():
                if outcome == "switched":
                    self.log.switches[name] = self.log.switches.get(name, 0) + 1
                    for relay in self.prbs:
                        if relay.name == name:
                            relay.last_switch_ns = t_ns
                elif outcome == "deferred":
                    self.log.deferred += 1
                elif outcome in ("failed", "refused"):
                    self.log.failed += 1

    def record(self, t_ns: int) -> None:
        """``/ident/relays``: the relays as written at this tick, and their switch-ons."""
        written = self.rig.bench.commanded()
        message: dict[str, int] = {}
        for name in self.recorded:
            on = written[name]
            message[name] = int(on)
            message[f"{name}_start"] = int(on and not self._previous[name])
            self._previous[name] = on
        self._topic.log(t_ns, message)
        self._progress(t_ns)


def plan_experiment(opts: IdentifyOptions, config: BenchConfig
                    ) -> tuple[list[str], list[str], list[str], dict[str, float]]:
    """(PRBS relays, relays the sequence plays, machining relays, min hold per PRBS relay);
    bad options -> UsageError."""
    if opts.machining not in MACHINING_MODES:
        raise UsageError(f"--machining must be one of {', '.join(MACHINING_MODES)}, "
                         f"got {opts.machining!r}")
    relays = config.map.relays
    machining = list(config.problem.sequence.relays)
    unknown = [n for n in opts.relays if n not in relays]
    if unknown:
        raise UsageError(f"--relays: unknown relay(s) {', '.join(unknown)} (relays of the "
                         f"bench: {', '.join(relays)})")
    clash = [n for n in opts.relays if n in machining and opts.machining != "off"]
    if clash:
        raise UsageError(f"--relays {','.join(clash)}: played by --machining {opts.machining};"
                         " leave them out of --relays or use --machining off")
    prbs = list(opts.relays) + (machining if opts.machining == "prbs" else [])
    if not prbs and opts.machining != "sequence":
        raise UsageError("nothing to switch: name --relays or use --machining sequence|prbs")
    holds: dict[str, float] = {}
    for name in prbs:
        dwell = relays[name].dwell_s
        hold = dwell if opts.min_hold_s is None else opts.min_hold_s
        if hold < dwell:
            raise UsageError(f"--min-hold {opts.min_hold_s:g} s is shorter than the dwell of "
                             f"{name} ({dwell:g} s): the safety layer would defer switches")
        holds[name] = hold
    played = machining if opts.machining == "sequence" else []
    return prbs, played, machining, holds


def run_identify_experiment(opts: IdentifyOptions, stream: TextIO | None = None
                            ) -> dict[str, Any]:
    """Run one PRBS experiment; return its summary (``hil bench identify``)."""
    # here, not at the top: the command line imports this module, and reading a bench config
    # imports the driver and the emulator (pymodbus)
    from hil.bench.config import default_text, load_bench_config

    if not (opts.duration_s > 0 and math.isfinite(opts.duration_s)):
        raise UsageError(f"--duration must be a positive number of seconds, got "
                         f"{opts.duration_s:g}")
    config = load_bench_config(opts.config_path)
    prbs_names, played, machining, holds = plan_experiment(opts, config)
    sample_s = config.sampling.period_s
    quantities = config.map.meter_quantities
    if opts.meter_quantity not in quantities:
        raise UsageError(f"--output-quantity {opts.meter_quantity!r} is not polled (meter "
                         f"quantities: {', '.join(quantities)})")
    out = opts.out or default_session_path("bench", "identify")
    prbs = [PrbsRelay(name, max(1, math.ceil(holds[name] / sample_s - 1e-9)),
                      config.map.relays[name].dwell_s, np.random.default_rng([opts.seed, k]))
            for k, name in enumerate(prbs_names)]
    recorded = prbs_names + played
    run = vars(opts) | {"prbs": prbs_names, "sequence": played, "min_hold_s": holds}
    text = "\n".join(filter(None, [default_text("bench.toml"), config.user_text]))
    # the bench first, as a run opens it: hil's emulator at a URL takes the run's time over
    # the wire (lockstep); any other bench keeps the wall clock
    events = EventBuffer()
    planned = planned_clock(opts.realtime)
    device = open_bench_device(opts.bench or config.bus.url, config, planned, events)
    clock = device.clock or planned
    rig = None
    try:
        session = Session(out, clock, sample_s, kind="bench-identify",
                          config={"bench": config.data, "run": run}, config_text=text)
    except BaseException:
        device.close()
        raise
    events.attach(session)
    log = ExperimentLog()
    try:
        rig = attach_rig(session, config, device, play_sequence=bool(played))
        progress = _progress_printer(session, rig, log, opts, stream or sys.stderr)
        session.add_task(PrbsTask(rig, prbs, recorded, session, log, progress,
                                  rig.sampler.divisor))
        session.run(duration_s=opts.duration_s)
    except BaseException:
        if rig is None:
            device.close()
        else:
            rig.close()
        session.close()
        raise
    stats = rig.bench.stats
    rig.close()
    summary = {
        "mcap": out, "duration_s": opts.duration_s, "clock": clock.mode, "bench": opts.bench,
        "seed": opts.seed, "prbs_relays": prbs_names, "sequence_relays": played,
        "min_hold_s": holds, "switches": {n: log.switches.get(n, 0) for n in prbs_names},
        "deferred_requests": stats.deferred_requests, "late_ticks": log.late_ticks,
        "failed_writes": log.failed + stats.failed_writes, "link_losses": stats.link_losses,
        "samples": rig.sampler.samples, "missed_power": rig.sampler.missed_power,
        "stop_reason": session.loop.stop_reason,
        "identify_commands": identify_commands(out, recorded, machining, opts.meter_quantity),
    }
    session.close(kpis={k: v for k, v in summary.items() if k != "identify_commands"})
    return summary


def _progress_printer(session: Session, rig: BenchRig, log: ExperimentLog,
                      opts: IdentifyOptions, stream: TextIO) -> Callable[[int], None]:
    every_ns = round(opts.progress_s * 1e9)
    t0_ns: int | None = None
    next_ns = every_ns

    def progress(t_ns: int) -> None:
        nonlocal t0_ns, next_ns
        if t0_ns is None:
            t0_ns = t_ns
        elapsed = t_ns - t0_ns
        if every_ns <= 0 or elapsed < next_ns:
            return
        next_ns += every_ns
        power = rig.sampler.latest_power or {}
        value = power.get(opts.meter_quantity, math.nan)
        switches = sum(log.switches.values())
        print(f"hil bench identify: t = {elapsed / 1e9:6.1f} / {opts.duration_s:g} s, "
              f"{switches} switches, {log.deferred} deferred, "
              f"{opts.meter_quantity} {value:.1f}", file=stream, flush=True)

    return progress


def identify_commands(path: str, switched: list[str], machining_relays: list[str],
                      quantity: str) -> list[dict[str, str]]:
    """The ``hil identify`` command lines for the loads switched in the session.

    A model per load group (each peripheral; the machining relays together) when the session
    switched only that group. When several groups switched, the other groups would count as
    unexplained output in a one-group model: the command then names every switched relay as
    an input (one joint model) - for the EEC's per-device model files, record one experiment
    per group.
    """
    machining = [n for n in switched if n in machining_relays]
    groups: dict[str, list[str]] = {n: [n] for n in switched if n not in machining}
    if machining:
        groups["machining"] = machining
    stem = os.path.splitext(path)[0]
    output = f"/bench/power:{quantity}"

    def command(target: str, names: list[str]) -> str:
        argv = ["hil", "identify", path]
        for name in names:
            # the switch-on event as a 2nd input: a linear model needs it to hold a motor's
            # inrush, and the UPS ramping up slower than it drops (machining: 98.6 % vs 88.9 %)
            argv += ["--input", f"{TOPIC}:{name}", "--input", f"{TOPIC}:{name}_start"]
        argv += ["--output", output, "--order", "3", "--detrend", "--no-feedthrough",
                 "--out", f"{stem}.{target}.json"]
        return shlex.join(argv)

    if len(groups) == 1:
        target, names = next(iter(groups.items()))
        return [{"target": target, "command": command(target, names)}]
    every = [n for names in groups.values() for n in names]
    return [{"target": "+".join(groups), "command": command("joint", every)}]
