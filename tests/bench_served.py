"""Serve what a ``hil emulate bench`` process serves, from this process (its own threads), for
a test whose point is not the emulator's process (:func:`bench_served_here`)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace

from hil.bench.config import load_bench_config
from hil.emulation import ServedBench, serve_bench
from hil.emulators.faults import for_emulator, parse_fault


@dataclass
class BenchHere:
    """A bench emulator served in this process: ``url`` is where a driver reaches it."""

    url: str
    served: ServedBench
    faults_seen: list[str] = field(default_factory=list)
    clock_lines: list[str] = field(default_factory=list)

    def fault_events(self) -> list[str]:
        """The faults it started injecting so far (as ``EmulatorProcess.fault_events``)."""
        return list(self.faults_seen)


@contextlib.contextmanager
def bench_served_here(config: str | os.PathLike[str] | None = None, *,
                      tcp: tuple[str, int] | None = ("127.0.0.1", 0), serial: str | None = None,
                      clock: str = "auto", seed: int | None = None,
                      disturbance: bool | None = None, faults: Iterable[str] = ()
                      ) -> Iterator[BenchHere]:
    """What ``hil emulate bench --config CONFIG --tcp HOST:PORT (or --serial PORT) --clock C
    --seed S --fault F...`` serves (``disturbance``: ``--disturbance``), by this process until
    the block ends: for a test whose point is not the emulator's process (a ``hil emulate
    bench`` process costs some 0.35 s of CPU to start). ``clock_lines`` are what the process
    says of a master taking or letting go of the time (``hil: clock: LINE``)."""
    loaded = load_bench_config(None if config is None else os.fspath(config))
    loaded = replace(loaded, faults=tuple(for_emulator(
        [*loaded.faults, *map(parse_fault, faults)], "bench", "--fault")))
    seen: list[str] = []
    clock_lines: list[str] = []
    served = serve_bench(loaded.emulating(seed, disturbance), tcp=None if serial else tcp,
                         serial=serial, clock=clock, on_fault=seen.append,
                         on_clock=clock_lines.append)
    try:
        yield BenchHere(served.url, served, seen, clock_lines)
    finally:
        served.stop()
