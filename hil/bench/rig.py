"""A bench wired into a session: :func:`attach_rig` adds an opened bench
(:mod:`hil.bench.openers`) to a :class:`~hil.core.session.Session` with its tasks, first in
every phase (plant step, :mod:`~hil.bench.sampler`, :mod:`~hil.bench.link_monitor`, the
:mod:`~hil.bench.sequence` player), so a controller added after them sees this tick's sample.
:func:`attach_bench` opens the bench and attaches it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from hil.bench.emulator_time import WirePlantClock
from hil.bench.link_monitor import LinkMonitor
from hil.bench.openers import OpenedBench, open_bench_device
from hil.bench.readings import STALE_POLLS, StaleReadings
from hil.bench.sampler import BenchSampler
from hil.bench.sequence import SequencePlayer, SequenceSchedule
from hil.errors import ConfigError

if TYPE_CHECKING:
    from hil.bench.config import BenchConfig
    from hil.core.session import Session
    from hil.drivers.bench.safe_bench import SafeBench
    from hil.emulator_process import EmulatorProcess
    from hil.emulators.bench.server import EmulatedBench


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
