"""The bridge side of the relay bench: its config, the machining sequence, the loop tasks.

* :func:`load_bench_config` - ``hil/configs/bench.toml`` with a user file laid over it.
* :class:`MachiningSequence` - ``[sequence]`` for the player: exact nanosecond lookups on the
  table parsed by :func:`controllers.bench_problem.parse_sequence` (which the controllers use).
* :class:`BenchSampler` - polls power (and levels) every sample, services the safety layer,
  publishes ``/bench/power``, ``/bench/levels``, ``/bench/relays``.
* :class:`SequencePlayer` - drives M1/M2 from the table through the safety layer.
* :func:`attach_bench` - all of it wired into a :class:`~hil.core.session.Session`, against the
  emulator (in-process, lockstep or real time) or a real bench URL. Add controller tasks after
  it: tasks run in the order added, so a controller sees this tick's sample.
"""

from __future__ import annotations

import importlib.resources
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from controllers.bench_problem import Stage, parse_sequence
from hil.core.config import deep_merge, load_toml, lookup, parse_toml
from hil.core.errors import ConfigError
from hil.core.loop import Task

if TYPE_CHECKING:
    from drivers.safety import SafeBench
    from emulators.bench_server import EmulatedBench
    from hil.core.clock import Clock
    from hil.core.session import Session

SOURCE = "bench config"


def default_bench_config_text() -> str:
    """The packaged default bench config (TOML text, with its comments)."""
    return importlib.resources.files("hil.configs").joinpath("bench.toml").read_text("utf-8")


def load_bench_config(path: str | None = None) -> dict[str, Any]:
    """The default bench config, with the file at ``path`` (if any) laid over it."""
    config = parse_toml(default_bench_config_text(), "hil/configs/bench.toml")
    if path is not None:
        user, _text = load_toml(path)
        config = deep_merge(config, user)
    return config


class MachiningSequence:
    """The machining sequence as the bridge plays it: exact lookups in integer nanoseconds on
    the table parsed by :func:`controllers.bench_problem.parse_sequence`."""

    def __init__(self, period_s: float, stages: list[Stage]) -> None:
        self.period_s = period_s
        self.stages = stages
        self.relays = sorted(set().union(*(s.on for s in stages)))
        self._period_ns = round(period_s * 1e9)
        self._starts_ns = [round(s.start_s * 1e9) for s in stages]

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> MachiningSequence:
        table = parse_sequence(config)
        return cls(table.period_s, list(table.stages))

    def stage_at(self, t_ns: int) -> Stage:
        """The stage at ``t_ns`` after the sequence started (periodic)."""
        phase = t_ns % self._period_ns
        index = int(np.searchsorted(self._starts_ns, phase, side="right")) - 1
        return self.stages[index]

    def states_at(self, t_ns: int) -> dict[str, bool]:
        stage = self.stage_at(t_ns)
        return {name: name in stage.on for name in self.relays}

    def profile(self, dt_s: float) -> dict[str, np.ndarray]:
        """One period sampled every ``dt_s``: ``{relay: 0/1 array}`` (e.g. for predictions)."""
        n = round(self.period_s / dt_s)
        states = [self.states_at(round(k * dt_s * 1e9)) for k in range(n)]
        return {name: np.array([s[name] for s in states], dtype=np.int8)
                for name in self.relays}


def _number_schema(title: str, description: str, names: list[str]) -> dict[str, Any]:
    return {"type": "object", "title": title, "description": description,
            "properties": {name: {"type": "number"} for name in names}}


class BenchSampler(Task):
    """Every sample: service the safety layer, poll the meter (and levels), publish.

    A failed poll publishes nothing for that sample and is counted (``missed_power``); the
    latest good values stay in ``latest_power`` / ``latest_levels`` for controllers.
    """

    def __init__(self, bench: SafeBench, session: Session | None = None, *,
                 quantities: list[str], levels: list[str], levels_every: int = 1,
                 readback_every: int = 100, divisor: int = 1, name: str = "bench_io") -> None:
        super().__init__(name, divisor)
        if levels_every < 1 or readback_every < 0:
            raise ConfigError(f"{SOURCE}: sampling.levels_every must be >= 1 and "
                              "sampling.relays_readback_every >= 0")
        self.bench = bench
        self.levels_every, self.readback_every = levels_every, readback_every
        self.latest_power: dict[str, float] | None = None
        self.latest_levels: dict[str, float] | None = None
        self.samples = self.missed_power = self.missed_levels = 0
        self._topics = None
        if session is not None:
            relay_fields = [*bench.relay_names, *(f"{n}_commanded" for n in bench.relay_names)]
            self._topics = (
                session.topic("/bench/power", _number_schema(
                    "hil.BenchPower", "Power meter (SDM630 registers) of the bench", quantities)),
                session.topic("/bench/levels", _number_schema(
                    "hil.BenchLevels", "Resource levels q_j of the bench", levels)),
                session.topic("/bench/relays", {
                    "type": "object", "title": "hil.BenchRelays",
                    "description": "Relay states (1 = on): actual (verified) and commanded "
                                   "(including changes deferred by the dwell); link_up 0/1",
                    "properties": {f: {"type": "integer", "enum": [0, 1]}
                                   for f in [*relay_fields, "link_up"]},
                }),
            )

    def read(self, t_ns: int) -> tuple[dict[str, float] | None, dict[str, float] | None]:
        n = self.samples
        self.samples += 1
        bench = self.bench
        bench.service(t_ns)
        power = bench.read_power()
        levels = bench.read_levels() if n % self.levels_every == 0 else None
        if self.readback_every and n % self.readback_every == 0 and bench.link_up:
            bench.readback(t_ns)
        if power is None:
            self.missed_power += 1
        if levels is None and n % self.levels_every == 0:
            self.missed_levels += 1
        return power, levels

    def compute(self, measurement: Any, t_ns: int) -> Any:
        return measurement

    def write(self, command: Any, t_ns: int) -> None:
        power, levels = command
        if power is not None:
            self.latest_power = power
        if levels is not None:
            self.latest_levels = levels
        if self._topics is None:
            return
        power_topic, levels_topic, relays_topic = self._topics
        if power is not None:
            power_topic.log(t_ns, power)
        if levels is not None:
            levels_topic.log(t_ns, levels)
        actual, commanded = self.bench.relays(), self.bench.commanded()
        message: dict[str, int] = {name: int(on) for name, on in actual.items()}
        message.update({f"{name}_commanded": int(on) for name, on in commanded.items()})
        message["link_up"] = int(self.bench.link_up)
        relays_topic.log(t_ns, message)


class SequencePlayer(Task):
    """Plays the machining sequence on its relays from the first tick on (``t0_ns``)."""

    def __init__(self, bench: SafeBench, sequence: MachiningSequence, *, divisor: int = 1,
                 name: str = "sequence") -> None:
        super().__init__(name, divisor)
        self.bench, self.sequence = bench, sequence
        self.t0_ns: int | None = None

    def phase_s(self, t_ns: int) -> float:
        """Time into the current machine cycle (0 before the first tick)."""
        if self.t0_ns is None:
            return 0.0
        return ((t_ns - self.t0_ns) % round(self.sequence.period_s * 1e9)) / 1e9

    def read(self, t_ns: int) -> dict[str, bool]:
        if self.t0_ns is None:
            self.t0_ns = t_ns
        return self.sequence.states_at(t_ns - self.t0_ns)

    def compute(self, measurement: dict[str, bool], t_ns: int) -> dict[str, bool]:
        commanded = self.bench.commanded()
        return {name: on for name, on in measurement.items() if commanded[name] != on}

    def write(self, command: dict[str, bool], t_ns: int) -> None:
        if command and self.bench.link_up:
            self.bench.set_relays(command, t_ns)


def open_bench(url: str, config: Mapping[str, Any], clock: Clock, on_event: Any = None
               ) -> SafeBench:
    """Driver + safety layer for the bench at ``url``, opened (relays at safe levels)."""
    from drivers.modbus_bench import BenchMap, ModbusBenchDriver, ModbusLink, parse_bus_url
    from drivers.safety import SafeBench

    link = ModbusLink(parse_bus_url(url), lookup(config, "bus.timeout_s", float, source=SOURCE),
                      lookup(config, "bus.attempts", int, source=SOURCE))
    driver = ModbusBenchDriver(link, BenchMap.from_config(config))
    bench = SafeBench(
        driver, clock, on_event=on_event,
        watchdog_polls=lookup(config, "bus.watchdog_polls", int, source=SOURCE),
        reconnect_interval_s=lookup(config, "bus.reconnect_interval_s", float, source=SOURCE),
    )
    try:
        bench.open()
    except BaseException:
        driver.close()
        raise
    return bench


@dataclass
class BenchRig:
    """A bench attached to a session: the safe facade, the tasks, the emulator if any."""

    bench: SafeBench
    sampler: BenchSampler
    player: SequencePlayer | None
    sequence: MachiningSequence
    emulator: EmulatedBench | None
    config: dict[str, Any]

    def close(self) -> None:
        """After the run (the loop already drove the relays safe): close link, stop emulator."""
        try:
            self.bench.close()
        finally:
            if self.emulator is not None:
                self.emulator.stop()


def attach_bench(session: Session, config: Mapping[str, Any], target: str | None = None, *,
                 play_sequence: bool = True, seed: int | None = None,
                 disturbance: bool | None = None) -> BenchRig:
    """Wire the bench into ``session``: [emulator step (lockstep)], sampler, sequence player.

    ``target``: ``"emulated"`` (an in-process emulator on 127.0.0.1, a free port; stepped by
    the loop when the session clock is a SimClock, by the wall clock otherwise) or a bus URL;
    default ``bus.url`` of the config. The bench is a session component: its relays go to
    their safe levels when the loop stops, whatever the reason.
    """
    config = dict(config)
    sequence = MachiningSequence.from_config(config)
    period = lookup(config, "sampling.period_s", float, source=SOURCE)
    base_s = session.loop.base_period_ns / 1e9
    divisor = round(period / base_s)
    if divisor < 1 or abs(divisor * base_s - period) > 1e-9:
        raise ConfigError(f"{SOURCE}: sampling.period_s = {period:g} s is not a multiple of the "
                          f"loop's base period {base_s:g} s")
    target = target or lookup(config, "bus.url", str, source=SOURCE)
    emulator = None
    url = target
    if target == "emulated":
        from emulators.bench_server import EmulatedBench

        emulator = EmulatedBench(config, seed=seed, disturbance=disturbance)
        url = emulator.serve_tcp()
        if session.clock.mode == "sim":
            session.add_task(emulator.step_task())
        else:
            emulator.run_realtime()
    try:
        bench = open_bench(url, config, session.clock, session.event)
    except BaseException:
        if emulator is not None:
            emulator.stop()
        raise
    from drivers.modbus_bench import BenchMap

    bench_map = BenchMap.from_config(config)
    sampler = BenchSampler(
        bench, session, quantities=bench_map.meter_quantities, levels=bench_map.level_names,
        levels_every=lookup(config, "sampling.levels_every", int, 1, source=SOURCE),
        readback_every=lookup(config, "sampling.relays_readback_every", int, 100, source=SOURCE),
        divisor=divisor,
    )
    session.add_task(sampler)
    player = None
    if play_sequence:
        player = SequencePlayer(bench, sequence, divisor=divisor)
        session.add_task(player)
    session.add_component(bench)
    return BenchRig(bench, sampler, player, sequence, emulator, config)
