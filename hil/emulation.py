"""Emulators served in this process until they are stopped: what ``hil emulate`` runs.

:func:`serve_bench` starts hil's bench emulator on Modbus TCP or RTU, :func:`serve_drives`
emulated CiA 402 drives on a socketcand server, :func:`serve_ethercat_drives` the same drives
as EtherCAT slaves on a network interface; :func:`serve_until_stopped` serves each
until SIGTERM or Ctrl-C (:class:`StopFlag`), with its state on the live view when asked
(:func:`live_state`), then stops it. The command line (:mod:`hil.cli.emulate`) parses the
flags and prints; :mod:`hil.emulator_process` runs that command in a process of its own.
"""

from __future__ import annotations

import contextlib
import secrets
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from hil.bench.config import BenchConfig
    from hil.core.realtime import Hardening, Step
    from hil.drivers.canopen.can_log import CanLog
    from hil.emulators.bench.server import EmulatedBench
    from hil.emulators.drive.bank import DriveBank
    from hil.emulators.drive.config import DriveEmulatorConfig
    from hil.emulators.drive.node import DriveNode
    from hil.emulators.ethercat.segment import EmulatedSegment
    from hil.emulators.faults import Fault
    from hil.emulators.socketcand_server import SocketcandServer
    from hil.protocols.can_frames import Frame

BENCH_LIVE_HZ = 10.0   # the emulators' state on --live: a modest rate, off their serving thread
DRIVE_LIVE_HZ = 50.0

#: the live view's topics: name -> (schema title, sampler)
Topics = dict[str, tuple[str, Callable[[], dict[str, Any]]]]


class StopFlag:
    """A stop request a signal handler may set: a plain store, no lock. (``Event.set()`` in a
    handler takes the lock the interrupted ``Event.wait()`` may hold: two SIGTERMs a few ms
    apart once hung ``hil emulate bench`` for minutes.) ``is_set``/``wait`` poll it."""

    POLL_S = 0.05

    def __init__(self) -> None:
        self.requested = False

    def set(self) -> None:
        self.requested = True

    def is_set(self) -> bool:
        return self.requested

    def wait(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not self.requested and time.monotonic() < deadline:
            time.sleep(min(self.POLL_S, max(deadline - time.monotonic(), 0.0)))
        return self.requested


@contextlib.contextmanager
def until_stopped() -> Iterator[StopFlag]:
    """A flag that SIGTERM sets; Ctrl-C ends the block quietly. Restores the SIGTERM handler,
    except after a SIGTERM: the process is on its way out, and a second SIGTERM a few ms later
    (a supervisor's retry) is ignored instead of killing it in the middle of its exit."""
    stop = StopFlag()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        yield stop
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN if stop.requested else previous)


def _number_schema(title: str, sample: dict[str, Any]) -> dict[str, Any]:
    kinds = {bool: "integer", int: "integer", float: "number", str: "string"}
    return {"type": "object", "title": title, "properties": {
        name: {"type": kinds.get(type(value), "number")} for name, value in sample.items()}}


@contextlib.contextmanager
def live_state(address: str | None, topics: Topics, hz: float) -> Iterator[str | None]:
    """With a live view ``address``: serve ``topics`` every ``1/hz`` s of wall time from a
    thread, and ``/events`` at start and stop, and give the view's URL; without one, nothing
    (None)."""
    if address is None:
        yield None
        return
    from hil.core.recording.live import LiveSink, parse_address
    from hil.core.recording.recorder import EVENT_SCHEMA

    sink = LiveSink(*parse_address(address), rates={name: 0 for name in topics})
    sink.add_topic("/events", "/events", EVENT_SCHEMA)
    for name, (title, sample) in topics.items():
        sink.add_topic(name, name, _number_schema(title, sample()))
    stop = threading.Event()

    def event(kind: str, message: str) -> None:
        sink.log("/events", time.time_ns(), {"level": "info", "source": "emulator",
                                             "kind": kind, "message": message, "data": {}})

    def publish() -> None:
        from hil.core.realtime import ordinary_thread

        ordinary_thread()  # not the hardened serving thread's scheduling, if it is one
        event("emulator.start", "emulator serving")
        while not stop.wait(1.0 / hz):
            now = time.time_ns()
            for name, (_, sample) in topics.items():
                sink.log(name, now, sample())

    publisher = threading.Thread(target=publish, name="live-state", daemon=True)
    publisher.start()
    try:
        yield sink.url
    finally:
        stop.set()
        publisher.join()
        event("emulator.stop", "emulator stopped")
        sink.close()


class Served(Protocol):
    """An emulator serving in this process, as :func:`serve_until_stopped` runs it."""

    def state(self) -> Topics:
        """The live view's topics."""
        ...

    def serve(self, stop: StopFlag) -> None:
        """Serve until ``stop`` is set."""
        ...

    def stop(self) -> None:
        """Stop serving, for good."""
        ...


def serve_until_stopped(served: Served, live: str | None, hz: float,
                        on_ready: Callable[[str | None], None],
                        on_stopped: Callable[[], None]) -> None:
    """Serve ``served`` until SIGTERM or Ctrl-C, its state on the live view at ``live`` (if
    any) ``hz`` times a second, then stop it. ``on_ready`` is called (with the live view's
    URL) once a SIGTERM is handled, before serving; ``on_stopped`` once it stopped, whatever
    the reason."""
    # the stop flag is set before the ready line: a SIGTERM after it is handled
    with until_stopped() as stop, live_state(live, served.state(), hz) as live_url:
        try:
            on_ready(live_url)
            served.serve(stop)
        finally:  # Ctrl-C (KeyboardInterrupt, ended quietly by until_stopped) too
            served.stop()
            on_stopped()


@dataclass
class ServedBench:
    """hil's bench emulator serving in this process at ``url`` since ``started`` (monotonic
    seconds)."""

    emulator: EmulatedBench
    url: str
    started: float

    def state(self) -> Topics:
        """Meter, levels and coils of the plant of now (a lockstep master's session starts a
        new one)."""
        emulator = self.emulator

        def coils() -> dict[str, Any]:
            return {f"coil_{i}": int(on) for i, on in enumerate(emulator.plant.coils())}

        def meter() -> dict[str, Any]:
            return {"t_s": emulator.plant.t_s, **emulator.plant.snapshot.meter}

        def levels() -> dict[str, Any]:
            return dict(emulator.plant.snapshot.levels)

        return {"/bench/power": ("hil.BenchPower", meter), "/bench/levels": ("hil.BenchLevels",
                levels), "/emulator/coils": ("hil.EmulatorCoils", coils)}

    def serve(self, stop: StopFlag) -> None:
        """The emulator serves from threads of its own: wait for ``stop``."""
        while not stop.wait(0.2):
            pass

    def stop(self) -> None:
        self.emulator.stop()


def serve_bench(config: BenchConfig, *, tcp: tuple[str, int] | None = None,
                serial: str | None = None, baudrate: int = 115200, parity: str = "N",
                stopbits: int = 1, clock: str = "auto",
                on_clock: Callable[[str], None] | None = None,
                on_fault: Callable[[str], None] | None = None) -> ServedBench:
    """hil's bench emulator of ``config`` serving Modbus TCP at ``tcp`` (host, port), else
    Modbus RTU on the ``serial`` port, on the wall clock or a lockstep master's time
    (``clock``: a master taking or letting go of the time is told to ``on_clock``); each
    fault is told to ``on_fault`` as it starts."""
    from hil.bench.emulated import make_emulator

    emulator = make_emulator(config, on_fault)
    if tcp is not None:
        url = emulator.serve_tcp(*tcp)
    else:
        assert serial is not None, "serve_bench needs tcp or serial"
        url = emulator.serve_serial(serial, baudrate=baudrate, parity=parity,
                                    stopbits=stopbits)
    emulator.follow(clock, on_clock)
    return ServedBench(emulator, url, time.monotonic())


@dataclass
class ServedDrives:
    """Emulated CiA 402 drives, one per node id, on one socketcand server; every frame
    received and sent goes to ``trace`` too, if any. ``bank`` runs their steady lockstep
    cycles (None: each node's own path)."""

    server: SocketcandServer
    nodes: list[DriveNode]
    trace: CanLog | None = None
    bank: DriveBank | None = None
    hardening: Hardening | None = None  # the serving thread's, once hardened
    hardened: bool = False              # its real-time steps in force now

    def harden(self) -> list[Step]:
        """Serve as a real-time loop's answering helper (the calling thread must be the one
        that serves) while the drives keep their own clock; each step, granted or refused.
        Hardened, it answers on the loop's core, above the loop
        (:meth:`~hil.core.realtime.Hardening.for_answering_helper`), and does not poll for
        the next SYNC: the master's send wakes it on that core, where polling would keep the
        master from sending. While the drives keep a lockstep master's time the thread is an
        ordinary one again, polling for the master's next SYNC: real time buys nothing there."""
        from hil.core.realtime import Hardening

        _short_switch_interval()
        self.hardening = Hardening.for_answering_helper()
        steps = self.hardening.apply()
        self._set_hardened(True)
        service = self.server.on_tick

        def follow_the_clock_then_serve() -> None:
            self._follow_the_clock()
            if service is not None:
                service()

        self.server.on_tick = follow_the_clock_then_serve
        return steps

    def _follow_the_clock(self) -> None:
        assert self.hardening is not None
        on_master_time = self.nodes[0].on_master_time
        if on_master_time and self.hardened:
            self.hardening.restore()
            self._set_hardened(False)
        elif not on_master_time and not self.hardened:
            self.hardening.apply()
            self._set_hardened(True)

    def _set_hardened(self, hardened: bool) -> None:
        """Its real-time steps in force, or not. On SCHED_FIFO (the loop's core) it neither
        polls for the next SYNC nor wakes up for its time service, which follows the frames;
        otherwise it polls."""
        assert self.hardening is not None
        self.hardened = hardened
        real_time = self.hardening.real_time
        self.server.next_frame_ns = None if real_time else self.nodes[0].next_sync_ns
        self.server.service_follows_frames = real_time

    def state(self) -> Topics:
        """Each drive's axis and state machine."""
        return {("/emulator/drive" if len(self.nodes) == 1 else f"/emulator/drive/{node.node_id}"):
                ("hil.EmulatorDrive", _drive_state(node)) for node in self.nodes}

    def serve(self, stop: StopFlag) -> None:
        """The server's selector loop, in this thread, until ``stop``."""
        self.server.serve(stop)

    def stop(self) -> None:
        self.server.close()
        if self.trace is not None:
            self.trace.close()


def with_serial(config: DriveEmulatorConfig, serial: int) -> DriveEmulatorConfig:
    """``config`` whose drive answers ``serial`` as its serial number (0x1018:4): a number
    of this emulator process (its low 7 bits the node id), by which a master that reaches
    its drive's URL again tells this drive from one an earlier process served there (the
    in-process emulator keeps the node id). A ``set`` of 0x1018:4 and a twin's (the vendor's
    identity) are left as they are."""
    from hil.protocols.cia301 import IDENTITY

    if config.eds is not None or any(key == (IDENTITY, 4) for key, _ in config.object_values):
        return config
    return replace(config, object_values=(((IDENTITY, 4), serial), *config.object_values))


def serve_drives(config: DriveEmulatorConfig, node_ids: list[int], host: str, port: int, *,
                 clock: str = "auto", faults: Sequence[Fault] = (),
                 can_log: str | None = None,
                 on_fault: Callable[[str], None] | None = None,
                 bank: bool = True) -> ServedDrives:
    """The emulated drives of ``config``, one per node id, each with its own axis, booted on
    a socketcand server at ``host``:``port`` (port 0: any free port); ``clock`` is their
    time, ``faults`` they play (each told to ``on_fault`` as it starts), ``can_log`` a file
    every CAN frame is written to. Each read's frames go to the nodes together, a lockstep
    master's steady cycle for every node in one pass (``bank``: False for each node's own
    path, as :class:`~hil.emulators.drive.runners.LockstepDrive`)."""
    from hil.emulators.drive.bank import DriveBank
    from hil.emulators.drive.node import DriveNode
    from hil.emulators.drive.runners import deliver
    from hil.emulators.socketcand_server import SocketcandServer

    server = SocketcandServer(host, port, channel=config.channel)
    send: Callable[[list[Any]], None] = server.broadcast
    trace = None
    if can_log:
        from hil.drivers.canopen.can_log import CanLog

        trace = CanLog(can_log, config.channel)
        send = _traced_send(server.broadcast, trace)
    # one drive per node id, each with its own axis, all hearing every frame of the bus
    boot = secrets.randbits(32) & ~0x7F
    nodes = [DriveNode(with_serial(replace(config, node_id=node_id), boot | node_id),
                       send=send, clock=clock, faults=faults, on_fault=on_fault)
             for node_id in node_ids]

    # each transmission's frames to the nodes that hear them, the steady ones in one pass
    inboxes: list[deque[Frame]] = [deque() for _ in nodes]
    banked = DriveBank(nodes, inboxes) if bank else None

    def handle(frames: list[Frame]) -> None:
        heard_ns = time.monotonic_ns()
        for frame in frames:
            for node, inbox in zip(nodes, inboxes, strict=True):
                if node.hears(frame[0]):
                    inbox.append(frame)
        deliver(nodes, inboxes, banked, heard_ns, service=False)

    def service() -> None:
        for node in nodes:
            node.service()

    server.on_frames = handle if trace is None else _traced_handle(handle, trace)
    server.on_tick = service
    server.next_frame_ns = nodes[0].next_sync_ns  # one SYNC for them all
    for node in nodes:
        node.boot()
    return ServedDrives(server, nodes, trace, banked)


@dataclass
class ServedEthercatDrives:
    """Emulated CiA 402 drives as a line of EtherCAT slaves on one interface."""

    segment: EmulatedSegment

    @property
    def nodes(self) -> list[DriveNode]:
        return [slave.node for slave in self.segment.slaves]

    def state(self) -> Topics:
        return {("/emulator/drive" if len(self.nodes) == 1 else f"/emulator/drive/{node.node_id}"):
                ("hil.EmulatorDrive", _drive_state(node)) for node in self.nodes}

    def serve(self, stop: StopFlag) -> None:
        """Frames answered in this thread until ``stop``."""
        self.segment.serve(stop)

    def stop(self) -> None:
        self.segment.close()


def serve_ethercat_drives(config: DriveEmulatorConfig, node_ids: list[int], iface: str, *,
                          clock: str = "auto", faults: Sequence[Fault] = (),
                          on_fault: Callable[[str], None] | None = None,
                          esi: str | None = None) -> ServedEthercatDrives:
    """The emulated drives of ``config`` as EtherCAT slaves in a line on ``iface`` (a raw
    socket: CAP_NET_RAW), one per node id (the slaves' order), each with its own axis;
    ``esi``: a vendor's ESI file their SII is built from (None: hil's defaults)."""
    from hil.emulators.ethercat.segment import EmulatedSegment
    from hil.emulators.ethercat.slave import EthercatDrive

    sii = None
    if esi is not None:
        from hil.emulators.ethercat.esi import sii_from_esi

        sii = sii_from_esi(esi)
    twin_of_esi = esi is not None and config.eds == esi  # its PDOs are the ESI's
    slaves = [EthercatDrive(replace(config, node_id=node_id), clock=clock, faults=faults,
                            on_fault=on_fault, sii=sii, pdos_from_sii=twin_of_esi,
                            last=i == len(node_ids) - 1)
              for i, node_id in enumerate(node_ids)]
    return ServedEthercatDrives(EmulatedSegment(iface, slaves))


def harden_serving_thread(hardening: Hardening | None = None) -> list[Step]:
    """The calling thread as a helper of a real-time loop (threads it starts later inherit
    it), by ``hardening`` (default: a helper's, :meth:`Hardening.for_helper`, kept by the
    caller to undo it): each step, granted or refused."""
    from hil.core.realtime import Hardening

    _short_switch_interval()
    return (hardening or Hardening.for_helper()).apply()


def _short_switch_interval() -> None:
    """Another thread of this process (live view, CAN log) holds the GIL 0.1 ms at most, not
    5, while the serving thread waits for it."""
    from hil.core.loop import REALTIME_SWITCH_INTERVAL_S

    sys.setswitchinterval(REALTIME_SWITCH_INTERVAL_S)


def _drive_state(node: Any) -> Callable[[], dict[str, Any]]:
    """The live view's sample of one emulated drive."""
    plant = node.plant

    def sample() -> dict[str, Any]:
        return {"t_s": plant.time_s, "position_deg": plant.position_deg,
                "velocity_deg_s": plant.velocity_deg_s, "current_mA": plant.applied_current_ma,
                "statusword": node.statusword, "sync_count": node.sync_count}

    return sample


def _traced_send(send: Callable[[list], None], trace: Any) -> Callable[[list], None]:
    def traced(frames: list) -> None:
        send(frames)
        trace.sent(frames)

    return traced


def _traced_handle(handle: Callable[[list[Frame]], None], trace: Any
                   ) -> Callable[[list[Frame]], None]:
    def traced(frames: list[Frame]) -> None:
        for frame in frames:
            trace.received(frame)
        handle(frames)

    return traced
