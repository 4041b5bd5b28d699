"""How the bench application reaches a bench: its URL opened, before its session exists.

* :data:`BENCH_DEVICES` - bench URL scheme -> factory (``modbus-tcp``, ``modbus-rtu``,
  ``emulated`` (:mod:`hil.bench.emulated`), and any scheme a package declares in the
  ``hil.bench_devices`` entry points). A Modbus URL asked to run in lockstep (a SimClock) is:
  when hil's emulator answers there (its device identification), it is given the run's time
  over the wire (:mod:`hil.bench.emulator_time`); any other device runs on the wall clock (the
  :class:`OpenedBench`'s ``clock``). :func:`planned_clock` is what a run asks for.
* :func:`open_bench_device` opens a bench URL: the Modbus driver and its safety layer
  (:func:`safe_bench`), relays at their safe levels, as an :class:`OpenedBench`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from hil.bench.emulator_time import PlantStepTask, WirePlantClock, lockstep_over_the_wire
from hil.contracts import EventSink, TimeSource, no_event
from hil.core.clock import Clock, RealtimeClock, SimClock
from hil.core.registry import SchemeRegistry, scheme_of

if TYPE_CHECKING:
    from hil.bench.config import BenchConfig
    from hil.drivers.bench.emulator_clock import Identity
    from hil.drivers.bench.lines import Line
    from hil.drivers.bench.modbus import ModbusBenchDriver
    from hil.drivers.bench.safe_bench import SafeBench
    from hil.emulator_process import EmulatorProcess
    from hil.emulators.bench.server import EmulatedBench

#: How the bench application opens a bench URL: ``factory(url, config, session)`` returns an
#: :class:`OpenedBench` (modules imported only when a URL with their scheme is opened).
BENCH_DEVICES = SchemeRegistry("bench", {
    "modbus-tcp": ("hil.bench.openers", "open_modbus"),
    "modbus-rtu": ("hil.bench.openers", "open_modbus"),
    "emulated": ("hil.bench.emulated", "open_emulated"),
}, "hil.bench_devices")


def is_emulated(url: str) -> bool:
    """Whether ``url`` is the in-process emulator."""
    return scheme_of(url) == "emulated"


def planned_clock(realtime: bool) -> Clock:
    """What a run asks for: the wall clock with ``realtime``, else lockstep, which a bench URL
    keeps only where hil's emulator answers (:func:`open_modbus`: ``OpenedBench.clock``)."""
    return RealtimeClock() if realtime else SimClock()


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
        """Let go of an emulator's time (the relays went safe on it), confirm the relays at
        their safe levels (read back; after a lost link the bench is reached again: an event
        when they cannot be confirmed, which makes the run unsafe and is a line on the
        terminal, :meth:`~hil.drivers.bench.safe_bench.SafeBench.confirm_safe`), close the
        link (relays safe, best effort), then stop the emulator."""
        try:
            if isinstance(self.plant_task, WirePlantClock):
                self.plant_task.clock.release()
            self.bench.confirm_safe()
            self.bench.close()
        finally:
            if self.emulator is not None:
                self.emulator.stop()


def modbus_driver(url: str, config: BenchConfig, line: Line | None = None
                  ) -> ModbusBenchDriver:
    """The Modbus driver of the bench at ``url`` (not connected yet), over ``line`` if
    given."""
    from hil.drivers.bench.modbus import ModbusBenchDriver, ModbusLink, parse_bus_url

    bus = config.bus
    return ModbusBenchDriver(ModbusLink(parse_bus_url(url), bus.timeout_s, bus.attempts, line),
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


def open_bench_device(url: str, config: BenchConfig, clock: Clock,
                      on_event: EventSink = no_event) -> OpenedBench:
    """The bench at ``url`` through :data:`BENCH_DEVICES`, opened (relays at their safe
    levels); ``clock`` paces it (and steps an emulator in lockstep)."""
    opened: OpenedBench = BENCH_DEVICES.open(url, config, clock, on_event)
    return opened
