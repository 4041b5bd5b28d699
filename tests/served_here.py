"""Serve what a ``hil emulate drive`` or ``hil emulate bench`` process serves from this process
(its own threads, the same loopback socket or pty), for a test whose point is not the
emulator's process: a process costs some 0.35-0.45 s of CPU to start. The product's
:func:`hil.emulation.serve_drives` and :func:`hil.emulation.serve_bench` serve; these only
start and stop them around a test's block."""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace

from hil.bench.config import load_bench_config
from hil.emulation import StopFlag, serve_bench, serve_drives
from hil.emulators.drive.node import DriveNode
from hil.emulators.faults import for_emulator, parse_fault
from hil.servo.config import load_drive_config


@dataclass
class ServedHere:
    """An emulator served in this process: ``url`` is where a master reaches it;
    ``clock_lines`` what the bench emulator's process says of a master taking or letting go of
    the time (``hil: clock: LINE``); ``nodes`` the drives served (none for a bench)."""

    url: str
    faults_seen: list[str] = field(default_factory=list)
    clock_lines: list[str] = field(default_factory=list)
    nodes: list[DriveNode] = field(default_factory=list)

    def fault_events(self) -> list[str]:
        """The faults it started injecting so far (as ``EmulatorProcess.fault_events``)."""
        return list(self.faults_seen)


@contextlib.contextmanager
def drive_served_here(config: str | os.PathLike[str] | None = None, *,
                      node: int | Iterable[int] = 1, clock: str = "auto",
                      faults: Iterable[str] = ()) -> Iterator[ServedHere]:
    """What ``hil emulate drive --config CONFIG --node N... --clock C --fault F...`` serves, on
    socketcand 127.0.0.1 and a free port, until the block ends."""
    nodes = [node] if isinstance(node, int) else list(node)
    emulator = load_drive_config(config).emulator
    here = ServedHere("")
    served = serve_drives(emulator, nodes, "127.0.0.1", 0, clock=clock,
                          faults=[*emulator.faults, *map(parse_fault, faults)],
                          on_fault=here.faults_seen.append)
    here.nodes = served.nodes
    stop = StopFlag()
    serving = threading.Thread(target=served.serve, args=(stop,), name="drive emulator",
                               daemon=True)
    serving.start()
    try:
        host, port = served.server.address
        here.url = f"socketcand://{host}:{port}"
        yield here
    finally:
        stop.set()
        serving.join(10)
        served.stop()


@contextlib.contextmanager
def bench_served_here(config: str | os.PathLike[str] | None = None, *,
                      tcp: tuple[str, int] | None = ("127.0.0.1", 0), serial: str | None = None,
                      clock: str = "auto", seed: int | None = None,
                      disturbance: bool | None = None, faults: Iterable[str] = ()
                      ) -> Iterator[ServedHere]:
    """What ``hil emulate bench --config CONFIG --tcp HOST:PORT (or --serial PORT) --clock C
    --seed S --fault F...`` serves (``disturbance``: ``--disturbance``), until the block
    ends."""
    loaded = load_bench_config(None if config is None else os.fspath(config))
    loaded = replace(loaded, faults=tuple(for_emulator(
        [*loaded.faults, *map(parse_fault, faults)], "bench", "--fault")))
    here = ServedHere("")
    served = serve_bench(loaded.emulating(seed, disturbance), tcp=None if serial else tcp,
                         serial=serial, clock=clock, on_fault=here.faults_seen.append,
                         on_clock=here.clock_lines.append)
    here.url = served.url
    try:
        yield here
    finally:
        served.stop()
