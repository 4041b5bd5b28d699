"""The bridge side of the relay bench: how a bench is reached, the loop tasks around it.

* :data:`BENCH_DEVICES` - bench URL scheme -> factory (``modbus-tcp``, ``modbus-rtu``,
  ``emulated``, and any scheme a package declares in the ``hil.bench_devices`` entry points).
  ``emulated`` is handled here only: the emulator in-process on 127.0.0.1 (a free port),
  stepped by the loop (:class:`~hil.bench.emulator_time.PlantStepTask`) when the session
  clock is a SimClock, by the wall clock otherwise, and the same Modbus driver talking to it.
  A Modbus URL asked to run in lockstep (a SimClock) is: when hil's emulator answers there
  (its device identification), it is given the run's time over the wire
  (:mod:`hil.bench.emulator_time`); any other device runs on the wall clock (the
  :class:`OpenedBench`'s ``clock``). :func:`planned_clock` is what a run asks for,
  :func:`session_clock` what a session made before the bench is opened gets.
* :class:`SequenceSchedule` - the machining sequence as the player plays it: exact
  nanosecond lookups on the table of :class:`hil.controllers.bench.problem.MachiningSequence`.
* :class:`BenchSampler` - polls power (and levels) every sample and services the safety
  layer (read phase), records ``/bench/power``, ``/bench/levels``, ``/bench/relays`` (record
  phase).
* :class:`SequencePlayer` - drives M1/M2 from the table through the safety layer.
* :func:`open_bench_device` opens a bench URL (before its session exists);
  :func:`attach_rig` wires it into a :class:`~hil.core.session.Session`: the rig's tasks come
  first in every phase (plant step, sampler, link monitor, player), so a controller added
  after them sees this tick's sample. :func:`attach_bench` does both.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hil.bench.emulator_time import PlantStepTask, WirePlantClock, lockstep_over_the_wire
from hil.contracts import EventSink, TimeSource, no_event
from hil.controllers.bench.problem import MachiningSequence, Stage
from hil.core.clock import Clock, RealtimeClock, SimClock
from hil.core.loop import Task
from hil.core.registry import SchemeRegistry, scheme_of
from hil.errors import ConfigError

#: polls in a row with a frozen reading before it is reported (0.5 s at 100 Hz)
STALE_POLLS = 50

if TYPE_CHECKING:
    from hil.bench.config import BenchConfig
    from hil.core.session import Session
    from hil.drivers.bench.emulator_clock import Identity
    from hil.drivers.bench.modbus import ModbusBenchDriver
    from hil.drivers.bench.safe_bench import SafeBench
    from hil.emulator_process import EmulatorProcess
    from hil.emulators.bench.server import EmulatedBench

#: How the bench application opens a bench URL: ``factory(url, config, session)`` returns an
#: :class:`OpenedBench` (modules imported only when a URL with their scheme is opened).
BENCH_DEVICES = SchemeRegistry("bench", {
    "modbus-tcp": ("hil.bench.rig", "open_modbus"),
    "modbus-rtu": ("hil.bench.rig", "open_modbus"),
    "emulated": ("hil.bench.rig", "open_emulated"),
}, "hil.bench_devices")


def is_emulated(url: str) -> bool:
    """Whether ``url`` is the in-process emulator."""
    return scheme_of(url) == "emulated"


def session_clock(url: str, realtime: bool = False) -> Clock:
    """For a session made before its bench is opened: lockstep (a SimClock) against the
    in-process emulator unless ``realtime``; any bench URL on the wall clock."""
    return RealtimeClock() if realtime or not is_emulated(url) else SimClock()


def planned_clock(realtime: bool) -> Clock:
    """What a run asks for: the wall clock with ``realtime``, else lockstep, which a bench URL
    keeps only where hil's emulator answers (:func:`open_modbus`: ``OpenedBench.clock``)."""
    return RealtimeClock() if realtime else SimClock()


class SequenceSchedule:
    """The machining sequence as the player plays it: exact lookups in integer nanoseconds
    on the stages of a :class:`~hil.controllers.bench.problem.MachiningSequence`."""

    def __init__(self, sequence: MachiningSequence) -> None:
        self.period_s = sequence.period_s
        self.stages = list(sequence.stages)
        self.relays = list(sequence.relays)
        self._period_ns = round(self.period_s * 1e9)
        self._starts_ns = [round(s.start_s * 1e9) for s in self.stages]

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
            # SDM630 registers are IEEE 754 float32: float32 on the wire loses nothing
            "properties": {name: {"type": "number", "x-cdr": "float32"} for name in names}}


class BenchSampler(Task):
    """Every sample: service the safety layer, poll the meter (and levels), publish.

    A failed poll publishes nothing for that sample and is counted (``missed_power``); the
    latest good values stay in ``latest_power`` / ``latest_levels`` for controllers, this
    sample's in ``fresh_power`` / ``fresh_levels`` (None when it brought none) for the tasks
    that look at each reading once.
    """

    def __init__(self, bench: SafeBench, session: Session | None = None, *,
                 quantities: list[str], levels: list[str], levels_every: int = 1,
                 readback_every: int = 100, divisor: int = 1, name: str = "bench_io",
                 stale: StaleReadings | None = None) -> None:
        super().__init__(name, divisor)
        self.bench = bench
        self.stale = stale
        self.bad = BadReadings(session.event if session is not None else no_event)
        self.levels_every, self.readback_every = levels_every, readback_every
        self.latest_power: dict[str, float] | None = None
        self.latest_levels: dict[str, float] | None = None
        # this sample's good readings (None: failed, bad or not polled this sample)
        self.fresh_power: dict[str, float] | None = None
        self.fresh_levels: dict[str, float] | None = None
        self.samples = self.missed_power = self.missed_levels = 0
        # this sample as read: power, levels, actual and commanded relays, link up
        self._sample: tuple[Any, Any, dict[str, bool], dict[str, bool], bool] | None = None
        self._topics = None
        if session is not None:
            relay_fields = [*bench.relay_names, *(f"{n}_commanded" for n in bench.relay_names)]
            self._topics = (
                session.topic("/bench/power", _number_schema(
                    "hil.BenchPower", "Power meter (SDM630 registers) of the bench", quantities),
                    high_rate=True),
                session.topic("/bench/levels", _number_schema(
                    "hil.BenchLevels", "Resource levels q_j of the bench", levels),
                    high_rate=True),
                session.topic("/bench/relays", {
                    "type": "object", "title": "hil.BenchRelays",
                    "description": "Relay states (1 = on): actual (verified) and commanded "
                                   "(including changes deferred by the dwell); link_up 0/1",
                    "properties": {f: {"type": "integer", "enum": [0, 1], "x-cdr": "uint8"}
                                   for f in [*relay_fields, "link_up"]},
                }, high_rate=True),
            )

    def read(self, t_ns: int) -> None:
        """Service the safety layer, poll the meter (and levels), check for frozen sensors;
        keep the relays' states as they were read, for the record."""
        n = self.samples
        self.samples += 1
        bench = self.bench
        bench.service(t_ns)
        power = bench.read_power()
        levels = bench.read_levels() if n % self.levels_every == 0 else None
        if self.readback_every and n % self.readback_every == 0 and bench.link_up:
            bench.readback(t_ns)
        if power is not None:
            power = self.bad.screen("meter", power, t_ns)
        if levels is not None:
            levels = self.bad.screen("levels", levels, t_ns)
        if power is None:
            self.missed_power += 1
        if levels is None and n % self.levels_every == 0:
            self.missed_levels += 1
        relays = bench.relays()
        if self.stale is not None:
            self.stale.check(power, levels, relays, t_ns)
        self.fresh_power, self.fresh_levels = power, levels
        if power is not None:
            self.latest_power = power
        if levels is not None:
            self.latest_levels = levels
        self._sample = (power, levels, relays, bench.commanded(), bench.link_up)

    def record(self, t_ns: int) -> None:
        """``/bench/power``, ``/bench/levels`` and ``/bench/relays`` of this sample."""
        if self._topics is None or self._sample is None:
            return
        power, levels, actual, commanded, link_up = self._sample
        power_topic, levels_topic, relays_topic = self._topics
        if power is not None:
            power_topic.log(t_ns, power)
        if levels is not None:
            levels_topic.log(t_ns, levels)
        message: dict[str, int] = {name: int(on) for name, on in actual.items()}
        message.update({f"{name}_commanded": int(on) for name, on in commanded.items()})
        message["link_up"] = int(link_up)
        relays_topic.log(t_ns, message)


class BadReadings:
    """Readings no sensor can give: a non-finite value (NaN, inf: a float32 register holding
    garbage). Such a reading is a fault: dropped like a failed poll (never published, never
    in the KPIs; the controller keeps the last good one), counted in ``readings``, one
    ``meter.bad_reading`` / ``levels.bad_reading`` event (error) per episode."""

    def __init__(self, on_event: EventSink = no_event) -> None:
        self.on_event = on_event
        self.readings = 0
        self.episodes = 0
        self._bad: dict[str, bool] = {}

    def screen(self, device: str, values: dict[str, float], t_ns: int
               ) -> dict[str, float] | None:
        """``values``, or None when one of them is not finite."""
        bad = {name: value for name, value in values.items() if not math.isfinite(value)}
        was_bad = self._bad.get(device, False)
        self._bad[device] = bool(bad)
        if not bad:
            return values
        self.readings += 1
        if not was_bad:
            self.episodes += 1
            self.on_event(f"{device}.bad_reading", f"{device} reading not finite "
                          f"({', '.join(f'{k} = {v}' for k, v in bad.items())}): dropped "
                          "until the readings are finite again", level="error", source="bench",
                          values={k: str(v) for k, v in bad.items()})
        return None


class StaleReadings:
    """Frozen sensors: the meter's registers bit-identical for ``polls`` polls in a row (its
    noise never repeats), or a level unchanged that long while its consumer or supplier
    relay is on (a known non-zero rate). One event per episode (``meter.stale``,
    ``levels.stale``, error); ``episodes`` counts them."""

    def __init__(self, polls: int, rates: dict[str, tuple[str, float, str, float]],
                 on_event: EventSink = no_event) -> None:
        self.polls, self.rates, self.on_event = polls, rates, on_event
        self.episodes = 0
        self._last: dict[str, Any] = {}
        self._runs: dict[str, int] = {}

    def check(self, power: dict[str, float] | None, levels: dict[str, float] | None,
              relays: dict[str, bool], t_ns: int) -> None:
        if power is not None:
            self._same("meter", tuple(power.values()), True, t_ns)
        if levels is not None:
            for name, value in levels.items():
                consumer, alpha, supplier, eta = self.rates.get(name, ("", 0.0, "", 0.0))
                rate = alpha * relays.get(consumer, False) + eta * relays.get(supplier, False)
                self._same(f"levels.{name}", value, rate != 0, t_ns)

    def _same(self, key: str, value: Any, should_move: bool, t_ns: int) -> None:
        same = should_move and self._last.get(key) == value
        self._last[key] = value
        run = self._runs[key] = self._runs.get(key, 0) + 1 if same else 0
        if run == self.polls:
            self.episodes += 1
            device = key.split(".")[0]
            self.on_event(f"{device}.stale", f"{key} unchanged for {self.polls + 1} polls: "
                          "the sensor looks frozen", level="error", source="bench",
                          reading=key)


class LinkMonitor(Task):
    """Every sample: the intervals the bench link was declared lost (``down``, clock ns) and
    the run's end when it stays lost ``give_up_s`` (event ``link.gave_up``, loop stopped with
    reason ``link lost``; the relays go to their safe level as at every stop), at once when
    ``peer_gone`` says the emulator the run is in lockstep with is gone (the link lost and
    given up on in the same sample), or as soon as a relay is found switched by someone else
    (``foreign``: event ``bench.foreign_master``)."""

    def __init__(self, bench: SafeBench, session: Session, give_up_s: float, divisor: int = 1,
                 name: str = "link", peer_gone: Callable[[], str | None] = lambda: None
                 ) -> None:
        super().__init__(name, divisor)
        self.bench, self.session = bench, session
        self.peer_gone = peer_gone
        self.give_up_ns = round(give_up_s * 1e9)
        self.down: list[list[int | None]] = []  # [lost at, restored at or None]
        self.gave_up = False
        self.foreign: str | None = None  # another master seen on the bench: the run stops

    def read(self, t_ns: int) -> None:
        if self.bench.stats.foreign_changes and self.foreign is None:
            self.foreign = ("a relay switched with no write of this run: another master is "
                            f"driving the bench at {self.bench.url}; the run stopped")
            self.session.event("bench.foreign_master", self.foreign, level="error",
                               source="bench")
            self.session.loop.stop("another master on the bench")
        gone = self.peer_gone()
        if gone is not None and not self.gave_up:
            self.bench.lose_link(gone)
        up = self.bench.link_up
        if not up and (not self.down or self.down[-1][1] is not None):
            self.down.append([t_ns, None])
        elif up and self.down and self.down[-1][1] is None:
            self.down[-1][1] = t_ns
        if self.gave_up:
            return
        if gone is not None:
            self._give_up(f"bench link lost: the bench emulator is gone ({gone}): the run stops",
                          f"link lost: the bench emulator is gone ({gone})")
            return
        if up or not self.give_up_ns:
            return
        lost_at = self.down[-1][0]
        assert lost_at is not None
        if t_ns - lost_at >= self.give_up_ns:
            seconds = self.give_up_ns / 1e9
            self._give_up(f"bench link lost for {seconds:g} s (bus.give_up_s): the run stops",
                          f"link lost for {seconds:g} s")

    def _give_up(self, message: str, reason: str) -> None:
        self.gave_up = True
        self.session.event("link.gave_up", message, level="error", source="bench")
        self.session.loop.stop(reason)

    def intervals(self, end_ns: int) -> list[tuple[int, int]]:
        """The lost intervals, an open one closed at ``end_ns``."""
        return [(a, b if b is not None else end_ns) for a, b in self.down if a is not None]


class SequencePlayer(Task):
    """Plays the machining sequence on its relays from the first tick on (``t0_ns``)."""

    def __init__(self, bench: SafeBench, sequence: SequenceSchedule, *, divisor: int = 1,
                 name: str = "sequence") -> None:
        super().__init__(name, divisor)
        self.bench, self.sequence = bench, sequence
        self.t0_ns: int | None = None
        self._changes: dict[str, bool] = {}

    def compute(self, t_ns: int) -> None:
        """The relays whose state in the table differs from what is commanded."""
        if self.t0_ns is None:
            self.t0_ns = t_ns
        states = self.sequence.states_at(t_ns - self.t0_ns)
        commanded = self.bench.commanded()
        self._changes = {name: on for name, on in states.items() if commanded[name] != on}

    def write(self, t_ns: int) -> None:
        if self._changes and self.bench.link_up:
            self.bench.set_relays(self._changes, t_ns)


class SequenceOrigin:
    """Clock time of the machining sequence's start, which every ``t_s`` counts from: the
    player's first tick (the clock's time until then)."""

    def __init__(self, clock: TimeSource) -> None:
        self.clock = clock
        self.player: SequencePlayer | None = None

    def __call__(self) -> int:
        t0 = self.player.t0_ns if self.player is not None else None
        return t0 if t0 is not None else self.clock.time_ns()


@dataclass
class OpenedBench:
    """What a bench factory returns: the safety layer, opened (relays at their safe levels),
    the emulator behind it, if any, to stop after the run, in lockstep the task that steps the
    emulator's plant (the rig makes it the first task), the clock the run goes by when it is
    not the one it was opened with (a bench URL asked for lockstep runs on the wall clock
    unless hil's emulator answers there), and the device's identification, if it gave one."""

    bench: SafeBench
    emulator: EmulatedBench | EmulatorProcess | None = None
    plant_task: PlantStepTask | WirePlantClock | None = None
    clock: Clock | None = None
    identity: Identity | None = None

    def peer_gone(self) -> str | None:
        """Lockstep over the wire: why the emulator is gone; None while it answers (and for
        any other bench)."""
        task = self.plant_task
        return task.gone if isinstance(task, WirePlantClock) else None

    def describe(self) -> dict[str, str]:
        """The session's ``bench`` metadata: where the bench is, what it said it is, whose
        time it follows."""
        wire = isinstance(self.plant_task, WirePlantClock)
        return {"url": self.bench.url,
                "identity": str(self.identity) if self.identity is not None else "",
                "time": ("the run's (lockstep over the wire)" if wire
                         else "the run's (in process)" if self.plant_task is not None
                         else "its own")}

    def close(self) -> None:
        """Let go of an emulator's time (the relays went safe on it) before the link closes,
        close the link (relays safe, best effort), then stop the emulator."""
        try:
            if isinstance(self.plant_task, WirePlantClock):
                self.plant_task.clock.release()
            self.bench.close()
        finally:
            if self.emulator is not None:
                self.emulator.stop()


def modbus_driver(url: str, config: BenchConfig) -> ModbusBenchDriver:
    """The Modbus driver of the bench at ``url`` (not connected yet)."""
    from hil.drivers.bench.modbus import ModbusBenchDriver, ModbusLink, parse_bus_url

    bus = config.bus
    return ModbusBenchDriver(ModbusLink(parse_bus_url(url), bus.timeout_s, bus.attempts),
                             config.map)


def open_safe(driver: ModbusBenchDriver, config: BenchConfig, clock: TimeSource,
              on_event: EventSink = no_event) -> SafeBench:
    """The safety layer over ``driver``, opened (relays at their safe levels); ``clock``
    paces the dwell, ``on_event`` records what happens. The driver is closed on failure."""
    from hil.drivers.bench.safe_bench import SafeBench

    bus = config.bus
    bench = SafeBench(driver, clock, on_event=on_event,
                      watchdog_polls=bus.watchdog_polls,
                      reconnect_interval_s=bus.reconnect_interval_s)
    try:
        bench.open()
    except BaseException:
        driver.close()
        raise
    return bench


def safe_bench(url: str, config: BenchConfig, clock: TimeSource,
               on_event: EventSink = no_event) -> SafeBench:
    """Modbus driver + safety layer for the bench at ``url``, opened (relays at their safe
    levels); ``clock`` paces the dwell, ``on_event`` records what happens."""
    return open_safe(modbus_driver(url, config), config, clock, on_event)


def open_modbus(url: str, config: BenchConfig, clock: Clock, on_event: EventSink
                ) -> OpenedBench:
    """Factory of ``modbus-tcp://HOST:PORT`` and ``modbus-rtu:///dev/X?...``. Asked for
    lockstep (a SimClock), it keeps it only where hil's emulator takes the run's time
    (:func:`lockstep_over_the_wire`); else the run follows the wall clock."""
    driver = modbus_driver(url, config)
    try:
        identity = plant_task = None
        if clock.mode == "sim":
            identity, plant_task = lockstep_over_the_wire(driver, config, on_event)
            if plant_task is None:
                clock = RealtimeClock()
        bench = open_safe(driver, config, clock, on_event)
    except BaseException:
        driver.close()
        raise
    return OpenedBench(bench, plant_task=plant_task, clock=clock, identity=identity)


def make_emulator(config: BenchConfig, on_fault: Callable[[str], None] | None = None
                  ) -> EmulatedBench:
    """The emulated bench of ``config`` (not serving yet), once the config is checked for it;
    it plays ``config.faults`` and tells ``on_fault`` of each one as it starts."""
    from hil.bench.config import check_emulation
    from hil.emulators.bench.server import EmulatedBench

    check_emulation(config)
    return EmulatedBench(config.plant, config.server, config.faults, on_fault)


def open_emulated(url: str, config: BenchConfig, clock: Clock, on_event: EventSink
                  ) -> OpenedBench:
    """Factory of ``emulated``. Lockstep (SimClock): the emulator in this process on
    127.0.0.1 (a free port), its plant stepped by the loop. Real time: the emulator in a
    process of its own, as the hardware would be, so the loop process measures only its own
    cost; it reads the same config file (``config.source``) with the plant's seed and
    disturbance switch."""
    if clock.mode != "sim":
        return _emulator_process(config, clock, on_event)
    emulator = make_emulator(config)
    tcp_url = emulator.serve_tcp()
    try:
        return OpenedBench(safe_bench(tcp_url, config, clock, on_event), emulator,
                           PlantStepTask(emulator, on_event=on_event))
    except BaseException:
        emulator.stop()
        raise


def _emulator_process(config: BenchConfig, clock: Clock, on_event: EventSink) -> OpenedBench:
    from hil.bench.config import check_emulation
    from hil.emulator_process import start_bench_emulator

    check_emulation(config)
    # the run's effective tables, every layer in (seed, disturbance...): what it was given
    process = start_bench_emulator(tables=config.data)
    on_event("emulator.process", f"bench emulator in process {process.pid} at {process.url}",
             source="bench", pid=process.pid, url=process.url)
    try:
        return OpenedBench(safe_bench(process.url, config, clock, on_event), process)
    except BaseException:
        process.stop()
        raise


def open_bench_device(url: str, config: BenchConfig, clock: Clock,
                      on_event: EventSink = no_event) -> OpenedBench:
    """The bench at ``url`` through :data:`BENCH_DEVICES`, opened (relays at their safe
    levels); ``clock`` paces it (and steps an emulator in lockstep)."""
    opened: OpenedBench = BENCH_DEVICES.open(url, config, clock, on_event)
    return opened


@dataclass
class BenchRig:
    """A bench attached to a session: the opened device, its tasks, the sequence."""

    device: OpenedBench
    sampler: BenchSampler
    link: LinkMonitor
    player: SequencePlayer | None
    sequence: SequenceSchedule
    config: BenchConfig

    @property
    def bench(self) -> SafeBench:
        return self.device.bench

    @property
    def emulator(self) -> EmulatedBench | EmulatorProcess | None:
        return self.device.emulator

    def close(self) -> None:
        """After the run (the loop already drove the relays safe): close link, stop emulator."""
        self.device.close()


def attach_rig(session: Session, config: BenchConfig, device: OpenedBench, *,
               play_sequence: bool = True) -> BenchRig:
    """Wire an opened bench into ``session``: its tasks, first in every phase, in this order:
    [plant step or time over the wire (lockstep emulator)], sampler, link monitor, [sequence
    player]. The bench is a session component: its relays go to their safe levels when the
    loop stops, whatever the reason. The session must run on the device's clock."""
    if device.clock is not None and device.clock is not session.clock:
        raise ConfigError(f"the bench at {device.bench.url} runs on the {device.clock.mode} "
                          f"clock, not on this session's {session.clock.mode} clock (lockstep "
                          "over the wire needs hil's emulator there)")
    period = config.sampling.period_s
    base_s = session.loop.base_period_ns / 1e9
    divisor = round(period / base_s)
    if divisor < 1 or abs(divisor * base_s - period) > 1e-9:
        raise ConfigError(f"{config.source}: sampling.period_s = {period:g} s is not a multiple "
                          f"of the loop's base period {base_s:g} s")
    bench, bench_map = device.bench, config.map
    rates = {r.name: (r.consumer, r.alpha, r.supplier, r.eta)
             for r in config.problem.resources}
    sampler = BenchSampler(
        bench, session, quantities=bench_map.meter_quantities, levels=bench_map.level_names,
        levels_every=config.sampling.levels_every,
        readback_every=config.sampling.relays_readback_every, divisor=divisor,
        stale=StaleReadings(STALE_POLLS, rates, session.event),
    )
    link = LinkMonitor(bench, session, config.bus.give_up_s, divisor,
                       peer_gone=device.peer_gone)
    sequence = SequenceSchedule(config.problem.sequence)
    player = SequencePlayer(bench, sequence, divisor=divisor) if play_sequence else None
    if isinstance(device.plant_task, WirePlantClock):
        device.plant_task.period_ns = session.loop.base_period_ns
    for task in (device.plant_task, sampler, link, player):
        if task is not None:
            session.add_task(task)
    session.add_component(bench)
    return BenchRig(device, sampler, link, player, sequence, config)


def attach_bench(session: Session, config: BenchConfig, target: str | None = None, *,
                 play_sequence: bool = True, seed: int | None = None,
                 disturbance: bool | None = None) -> BenchRig:
    """Open the bench at ``target`` (default ``bus.url`` of the config) and
    :func:`attach_rig` it; ``seed`` and ``disturbance`` override the emulated plant's."""
    device = open_bench_device(target or config.bus.url, config.emulating(seed, disturbance),
                               session.clock, session.event)
    try:
        return attach_rig(session, config, device, play_sequence=play_sequence)
    except BaseException:
        device.close()
        raise
