"""The ``emulated`` bench URL: hil's bench emulator, made from the bench config and opened.

Lockstep (a SimClock): the emulator in this process on 127.0.0.1 (a free port), stepped by
the loop (:class:`~hil.bench.emulator_time.PlantStepTask`), which holds its time as a master
over the wire does (no answer is late on a busy machine); the loop's driver hands its Modbus
TCP frames to the emulator's server in the loop's thread
(:class:`~hil.drivers.bench.lines.InProcessLine`). Real time: the emulator in a process of its
own (:mod:`hil.emulator_process`). Either way the same Modbus driver talks to it.
:func:`make_emulator` makes the emulated bench of a config for anyone who serves it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from hil.bench.emulator_time import PlantStepTask
from hil.bench.openers import OpenedBench, modbus_driver, open_safe, safe_bench
from hil.contracts import EventSink
from hil.core.clock import Clock

if TYPE_CHECKING:
    from hil.bench.config import BenchConfig
    from hil.emulators.bench.server import EmulatedBench


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
    from hil.drivers.bench.lines import InProcessLine

    emulator = make_emulator(config)
    # its frames go to the server in this thread: the same frames as over its socket (which
    # serves on for anyone else), without the socket and the hop to the server's thread
    line = InProcessLine(emulator.connect_in_process, config.bus.timeout_s)
    driver = modbus_driver(emulator.serve_tcp(), config, line)
    # the loop holds the plant's time: no answer is late, whatever else the machine does, and
    # a request waits as long as over the wire (a silence that long is a broken emulator)
    emulator.hold_in_process(config.bus.timeout_s)
    driver.link.hold_on(config.bus.lockstep_timeout_s)
    try:
        return OpenedBench(open_safe(driver, config, clock, on_event), emulator,
                           PlantStepTask(emulator, on_event=on_event))
    except BaseException:
        emulator.stop()
        raise


def _emulator_process(config: BenchConfig, clock: Clock, on_event: EventSink) -> OpenedBench:
    from hil.bench.config import check_emulation
    from hil.emulator_process import start_bench_emulator

    check_emulation(config)
    # the run's effective tables, every layer in (seed, disturbance...): what it was given;
    # hardened as the loop is (its steps: the session's realtime.emulator metadata)
    process = start_bench_emulator(tables=config.emulator_tables(), harden=True)
    on_event("emulator.process", f"bench emulator in process {process.pid} at {process.url}",
             source="bench", pid=process.pid, url=process.url, hardening=process.hardening)
    try:
        return OpenedBench(safe_bench(process.url, config, clock, on_event), process)
    except BaseException:
        process.stop()
        raise
