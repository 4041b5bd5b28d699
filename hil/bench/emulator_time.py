"""The emulated plant on the run's time, in lockstep: the emulator in the run's process
(:class:`PlantStepTask` steps it from the loop) or hil's emulator in a process of its own, at
a Modbus URL (:func:`lockstep_over_the_wire` asks the relay module who it is, and
:class:`WirePlantClock` gives hil's emulator the run's time over the wire). Either is the
rig's first task (:func:`hil.bench.rig.attach_rig`), so the same plant steps come between the
same reads and writes: the sessions are the same, bit for bit.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from hil.contracts import EventSink, no_event
from hil.core.loop import Task
from hil.core.notice import warn
from hil.errors import HilError
from hil.protocols.bench_clock import REVISION

if TYPE_CHECKING:
    from hil.bench.config import BenchConfig
    from hil.drivers.bench.emulator_clock import EmulatorClock, Identity
    from hil.drivers.bench.modbus import ModbusBenchDriver
    from hil.emulators.bench.server import EmulatedBench


class PlantStepTask(Task):
    """Lockstep: steps the emulated plant until its time matches the loop's clock (first task),
    and records every fault the emulator injected as a ``fault.injected`` event (the
    emulator's side of the story: what the bridge detects is recorded by the bridge)."""

    def __init__(self, emulator: EmulatedBench, name: str = "emulator",
                 on_event: EventSink = no_event) -> None:
        super().__init__(name, 1)
        self.emulator = emulator
        self.on_event = on_event
        self._t0_ns: int | None = None
        self._k0 = 0
        self._reported = 0

    def read(self, t_ns: int) -> None:
        plant = self.emulator.plant
        if self._t0_ns is None:
            self._t0_ns, self._k0 = t_ns, plant.k
        self.emulator.step(max(0, self._k0 + round((t_ns - self._t0_ns) / 1e9 / plant.dt)
                               - plant.k))
        events = self.emulator.faults.events
        while self._reported < len(events):
            event = events[self._reported]
            self._reported += 1
            self.on_event("fault.injected", f"emulator: {event['fault']} injected at plant "
                          f"t={event['t_s']:.2f} s", level="warning", source="emulator",
                          fault=event["fault"], plant_t_s=event["t_s"])


class WirePlantClock(Task):
    """Lockstep over the wire, hil's emulator in a process of its own: tells the emulator the
    time to step its plant to, on the bench's own connection, so the same plant steps come in
    the same order between the same reads and writes as :class:`PlantStepTask`'s. The time of
    the next tick is given at the end of each tick (record phase: after its writes, before the
    next tick's polls), posted without waiting for the answer (the emulator steps while the
    loop records), and written and answered every ``checked_every`` ticks: an emulator that
    stopped following (another master took its time) ends the run within that many ticks.
    ``gone`` says why the emulator is gone (no answer within ``bus.lockstep_timeout_s``,
    unreachable, refused), for the link monitor to end the run. ``period_ns``: the loop's
    base period (:func:`attach_rig` sets it)."""

    def __init__(self, clock: EmulatorClock, checked_every: int = 100,
                 name: str = "emulator") -> None:
        super().__init__(name, 1)
        self.clock, self.checked_every = clock, checked_every
        self.period_ns = 0
        self._t0_ns: int | None = None
        self._ticks = 0
        self._failed: str | None = None

    @property
    def gone(self) -> str | None:
        return self._failed or self.clock.link.gone

    def record(self, t_ns: int) -> None:
        if self._t0_ns is None:
            self._t0_ns = t_ns  # the plant is at the first tick's time: the session's start
        if self.gone is not None:
            return
        self._ticks += 1
        next_ns = t_ns + self.period_ns - self._t0_ns
        try:
            if self._ticks % self.checked_every:
                self.clock.post(next_ns)
            else:
                self.clock.advance(next_ns)
        except HilError as exc:  # the time cannot be given: the session is over
            self._failed = self.clock.link.gone or str(exc)


def lockstep_over_the_wire(driver: ModbusBenchDriver, config: BenchConfig, on_event: EventSink
                           ) -> tuple[Identity | None, WirePlantClock | None]:
    """Who the relay module says it is (the question may take ``bus.lockstep_timeout_s``, once),
    and, when it is hil's emulator, the task that gives it the run's time (its plant starts
    again from t = 0; every request may then take ``bus.lockstep_timeout_s``). None: the wall
    clock, for any other device, and for an emulator that keeps its wall clock or speaks
    another revision of the time protocol (a warning line and a ``bench.clock`` event)."""
    from hil.drivers.bench.emulator_clock import EmulatorClock, KeepsWallClockError, identify

    bound = config.bus.lockstep_timeout_s
    identity = identify(driver.link, config.map.units["relays"], bound)
    if identity is None or not identity.is_hil_emulator:
        return identity, None
    if not identity.speaks_our_clock:
        message = (f"the bench emulator at {driver.link.spec.url} speaks time protocol "
                   f"{identity.revision}, this hil {REVISION}: this run follows the wall clock, "
                   "as against a real bench (run the same hil on both sides)")
        warn(message)
        on_event("bench.clock", message, level="warning", source="bench")
        return identity, None
    clock = EmulatorClock(driver.link)
    try:
        with driver.link.patient(bound):
            clock.start(config.bus.timeout_s)
    except KeepsWallClockError as exc:
        warn(str(exc))
        on_event("bench.clock", str(exc), level="warning", source="bench")
        return identity, None
    driver.link.hold_on(bound)
    return identity, WirePlantClock(clock)
