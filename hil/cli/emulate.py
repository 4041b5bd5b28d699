"""``hil emulate bench|drive``: standalone emulator processes."""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

from hil.cli.argtypes import host_port, positive_int
from hil.cli.recording import add_live_arguments, live_address
from hil.core.config import load_toml
from hil.core.lifeline import die_with_parent
from hil.emulators.drive.timebase import CLOCKS
from hil.emulators.faults import (
    FORM,
    KINDS,
    Fault,
    for_emulator,
    parse_fault,
    parse_faults_table,
    print_event,
)
from hil.errors import ConfigError
from hil.protocols.bench_clock import CLOCKS as BENCH_CLOCKS

BENCH_LIVE_HZ = 10.0   # the emulators' state on --live: a modest rate, off their serving thread
DRIVE_LIVE_HZ = 50.0


def register(subparsers: argparse._SubParsersAction) -> None:
    emulate = subparsers.add_parser("emulate", help="run an emulator as a standalone process")
    emu_sub = emulate.add_subparsers(dest="emulate_command", metavar="DEVICE", required=True)
    eb = emu_sub.add_parser("bench", help="relay bench over Modbus TCP or RTU")
    where = eb.add_mutually_exclusive_group(required=True)
    where.add_argument("--tcp", type=host_port, metavar="HOST:PORT",
                       help="serve Modbus TCP here (port 0: any free port, printed)")
    where.add_argument("--serial", metavar="PORT",
                       help="serve Modbus RTU on this serial port, e.g. one end of a pty pair")
    eb.add_argument("--baud", type=positive_int, default=115200, help="RTU baud rate")
    eb.add_argument("--parity", choices=["N", "E", "O"], default="N", help="RTU parity")
    eb.add_argument("--stopbits", type=int, choices=[1, 2], default=1, help="RTU stop bits")
    eb.add_argument("--config", metavar="F.toml",
                    help="bench config laid over the default (hil/configs/bench.toml)")
    eb.add_argument("--seed", type=int, help="measurement noise seed (default: plant.seed)")
    eb.add_argument("--disturbance", action="store_true",
                    help="switch the unknown disturbance load on (plant.disturbance)")
    eb.add_argument("--clock", choices=BENCH_CLOCKS, default="auto",
                    help="the plant's time: auto (default: the wall clock, until a lockstep "
                    "master takes the time, as `hil bench run` without --realtime does, and "
                    "again when it lets go or closes its connection), wall (the wall clock "
                    "always: a lockstep master is refused, and says so in one line), master "
                    "(a master's time only: the plant waits for one). A master's session "
                    "starts the plant and its faults again from t = 0")
    _add_fault_arguments(eb, "bench", "delay@2-4:ms=300, drop@5-8, weld@3:relay=P1")
    add_live_arguments(eb, rates=False)
    eb.set_defaults(handler=emulate_bench_command)
    ed = emu_sub.add_parser("drive", help="CiA 402 servo drive over socketcand")
    ed.add_argument("--socketcand", type=host_port, metavar="HOST:PORT",
                    help="serve the socketcand protocol here (port 0: any free port, printed)")
    ed.add_argument("--write-eds", metavar="F.eds",
                    help="write the emulated drive's object dictionary as an EDS file (for "
                    "canopen's import_od, CANopen tools, `[master] eds`) and exit")
    ed.add_argument("--can-log", metavar="F.blf|F.asc|F.trc|F.log",
                    help="write every CAN frame the emulator receives and sends to this file "
                    "(python-can's can.Logger; the suffix picks the format)")
    ed.add_argument("--node", type=positive_int, action="append",
                    help="CANopen node id (1..127; default 1); repeat for several drives on "
                    "the bus, each with its own axis: --node 1 --node 2 --node 3")
    ed.add_argument("--config", metavar="F.toml",
                    help="drive config laid over the default (hil/configs/drive.toml); "
                    "its [emulator] table is used")
    ed.add_argument("--channel", help="bus name clients open (default: emulator.channel)")
    ed.add_argument("--harden", action="store_true",
                    help="serve as a real-time process where the OS allows (as `hil doctor` "
                    "reports): SCHED_FIFO below hil's loop, a core apart from the loop's, "
                    "locked memory; each step granted or refused is printed on stderr as "
                    "'hil: real-time: STEP granted|refused: ...' (hil servo run --realtime "
                    "asks for it)")
    ed.add_argument("--clock", choices=CLOCKS, default="auto",
                    help="the drives' time: auto (default: their own wall clock, until a "
                    "lockstep master asks for its SYNC time, as `hil servo run` does, and "
                    "again when it lets go or stays silent for longer than it said), sync (the "
                    "SYNCs' time from power-on: time passes only when SYNCs come), wall (their "
                    "own clock always: a lockstep master is told so and watches them on the "
                    "wall clock)")
    _add_fault_arguments(ed, "drive", "emcy@2:code=0x2310, no_heartbeat@1-3")
    add_live_arguments(ed, rates=False)
    ed.set_defaults(handler=emulate_drive_command)


def _fault(text: str) -> Fault:
    try:
        return parse_fault(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix(f"--fault {text!r}: ")
                                         ) from None


def _add_fault_arguments(parser: argparse.ArgumentParser, emulator: str, example: str) -> None:
    kinds = ", ".join(k for k, (where, _) in KINDS.items() if where == emulator)
    parser.add_argument("--fault", action="append", type=_fault, default=[], metavar="SPEC",
                        help=f"inject a fault (repeat): {FORM}, seconds since the emulator "
                        f"started, e.g. {example}. Kinds: {kinds}. Each is reported on "
                        "stderr as 'hil: fault: ...' when it starts")
    parser.add_argument("--faults", metavar="F.toml",
                        help="a file whose [faults] table (schedule = [...]) lists faults")


def faults_of(args: argparse.Namespace, emulator: str, configured: tuple[Fault, ...] = ()
              ) -> list[Fault]:
    """The faults of ``--faults F.toml`` and ``--fault`` (after ``configured``), checked."""
    faults = list(configured)
    if args.faults:
        data, _text = load_toml(args.faults)
        unknown = set(data) - {"faults"}
        if unknown:
            raise ConfigError(f"{args.faults}: unknown table {sorted(unknown)[0]!r} "
                              "(a faults file has only [faults])")
        faults += parse_faults_table(data.get("faults", {}), args.faults)
    faults += args.fault
    return for_emulator(faults, emulator, "--fault")


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


def _number_schema(title: str, sample: dict[str, Any]) -> dict[str, Any]:
    kinds = {bool: "integer", int: "integer", float: "number", str: "string"}
    return {"type": "object", "title": title, "properties": {
        name: {"type": kinds.get(type(value), "number")} for name, value in sample.items()}}


@contextlib.contextmanager
def _live_state(args: argparse.Namespace, topics: dict[str, tuple[str, Callable[[], dict]]],
                hz: float) -> Iterator[None]:
    """With ``--live``: serve ``topics`` (name -> (schema title, sampler)) every ``1/hz`` s of
    wall time from a thread, and ``/events`` at start and stop; without it, nothing."""
    address = live_address(args)
    if address is None:
        yield
        return
    from hil.core.live import LiveSink, parse_address
    from hil.core.recorder import EVENT_SCHEMA

    sink = LiveSink(*parse_address(address), rates={name: 0 for name in topics})
    sink.add_topic("/events", "/events", EVENT_SCHEMA)
    for name, (title, sample) in topics.items():
        sink.add_topic(name, name, _number_schema(title, sample()))
    print(f"hil: live view on {sink.url} (Foxglove: Open connection > Foxglove WebSocket)",
          file=sys.stderr, flush=True)
    stop = threading.Event()

    def event(kind: str, message: str) -> None:
        sink.log("/events", time.time_ns(), {"level": "info", "source": "emulator",
                                             "kind": kind, "message": message, "data": {}})

    def publish() -> None:
        event("emulator.start", "emulator serving")
        while not stop.wait(1.0 / hz):
            now = time.time_ns()
            for name, (_, sample) in topics.items():
                sink.log(name, now, sample())

    publisher = threading.Thread(target=publish, name="live-state", daemon=True)
    publisher.start()
    try:
        yield
    finally:
        stop.set()
        publisher.join()
        event("emulator.stop", "emulator stopped")
        sink.close()


@contextlib.contextmanager
def _until_stopped() -> Iterator[StopFlag]:
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


def emulate_bench_command(args: argparse.Namespace) -> int:
    """Serve the bench plant until Ctrl-C or SIGTERM, on the wall clock or a lockstep master's
    time (``--clock``); a master taking or letting go of the time is a line on stderr."""
    die_with_parent()
    from hil.bench.config import load_bench_config
    from hil.bench.emulated import make_emulator

    config = load_bench_config(args.config)
    config = replace(config, faults=tuple(faults_of(args, "bench", config.faults)))
    emulator = make_emulator(config.emulating(args.seed, args.disturbance or None), print_event)
    if args.tcp is not None:
        url = emulator.serve_tcp(*args.tcp)
    else:
        url = emulator.serve_serial(args.serial, baudrate=args.baud, parity=args.parity,
                                    stopbits=args.stopbits)
    emulator.follow(args.clock, lambda line: print(f"hil: clock: {line}", file=sys.stderr,
                                                   flush=True))
    units = emulator.devices.units
    started = time.monotonic()

    # the plant of now: a lockstep master's session starts a new one
    def coils() -> dict[str, Any]:
        return {f"coil_{i}": int(on) for i, on in enumerate(emulator.plant.coils())}

    def meter() -> dict[str, Any]:
        return {"t_s": emulator.plant.t_s, **emulator.plant.snapshot.meter}

    def levels() -> dict[str, Any]:
        return dict(emulator.plant.snapshot.levels)

    state = {"/bench/power": ("hil.BenchPower", meter), "/bench/levels": ("hil.BenchLevels",
             levels), "/emulator/coils": ("hil.EmulatorCoils", coils)}
    # the stop flag is set before the ready line: a SIGTERM after it is handled
    with _until_stopped() as stop, _live_state(args, state, BENCH_LIVE_HZ):
        try:
            print(f"hil: bench emulator listening on {url} (relays unit {units['relays']}, "
                  f"meter unit {units['meter']}, levels unit {units['levels']}); Ctrl-C stops",
                  flush=True)
            while not stop.wait(0.2):
                pass
        finally:  # Ctrl-C (KeyboardInterrupt, ended quietly by _until_stopped) too
            emulator.stop()
            print(f"hil: bench emulator stopped after {time.monotonic() - started:.1f} s "
                  f"(plant time {emulator.plant.t_s:.2f} s)", flush=True)
    return 0


def emulate_drive_command(args: argparse.Namespace) -> int:
    """Serve the emulated CiA 402 drive over socketcand in real time until Ctrl-C or SIGTERM."""
    die_with_parent()
    from hil.emulators.drive.node import DriveNode
    from hil.emulators.socketcand_server import SocketcandServer
    from hil.errors import UsageError
    from hil.servo.config import load_drive_config

    nodes_ids = args.node or [1]
    for node_id in nodes_ids:
        if not 1 <= node_id <= 127:
            raise UsageError(f"--node must be a CANopen node id 1..127, got {node_id}")
    if len(set(nodes_ids)) != len(nodes_ids):
        raise UsageError(f"--node given twice: {', '.join(map(str, nodes_ids))} (one drive per "
                         "node id on a bus)")
    overrides: dict[str, object] = {"node_id": nodes_ids[0]}
    if args.channel is not None:
        overrides["channel"] = args.channel
    emulator = load_drive_config(args.config, overrides={"emulator": overrides}).emulator
    if args.write_eds:
        return write_eds(emulator, args.write_eds)
    if args.socketcand is None:
        raise UsageError("hil emulate drive needs --socketcand HOST:PORT (or --write-eds F)")
    host, port = args.socketcand
    server = SocketcandServer(host, port, channel=emulator.channel)
    send: Callable[[list[Any]], None] = server.broadcast
    trace = None
    if args.can_log:
        from hil.drivers.canopen.can_log import CanLog

        trace = CanLog(args.can_log, emulator.channel)
        send = _traced_send(server.broadcast, trace)
    # one drive per node id, each with its own axis, all hearing every frame of the bus
    nodes = [DriveNode(replace(emulator, node_id=node_id), send=send, clock=args.clock,
                       faults=faults_of(args, "drive"), on_fault=print_event)
             for node_id in nodes_ids]

    def handle(msg: Any) -> None:
        for node in nodes:
            node.handle(msg)

    def service() -> None:
        for node in nodes:
            node.service()

    server.on_frame = handle if trace is None else _traced_handle(handle, trace)
    server.on_tick = service
    server.next_frame_ns = nodes[0].next_sync_ns  # one SYNC for them all
    for node in nodes:
        node.boot()
    bound_host, bound_port = server.address
    state = {("/emulator/drive" if len(nodes) == 1 else f"/emulator/drive/{node.node_id}"):
             ("hil.EmulatorDrive", _drive_state(node)) for node in nodes}
    ids = ", ".join(str(node.node_id) for node in nodes)
    # the stop flag is set before the ready line: a SIGTERM after it is handled
    with _until_stopped() as stop, _live_state(args, state, DRIVE_LIVE_HZ):
        try:
            if args.harden:  # the serving thread only, reported before the ready line
                _harden_serving_thread()
            print(f"hil: drive emulator node{'s' if len(nodes) > 1 else ''} {ids} on socketcand "
                  f"{bound_host}:{bound_port} (bus {emulator.channel}, clock {args.clock}); "
                  "Ctrl-C stops", flush=True)
            server.serve(stop)
        finally:  # Ctrl-C (KeyboardInterrupt, ended quietly by _until_stopped) too
            server.close()
            if trace is not None:
                trace.close()
            print(f"hil: drive emulator stopped after {nodes[0].sync_count} SYNC "
                  f"(plant time {nodes[0].plant.time_s:.3f} s)", flush=True)
    return 0


def _harden_serving_thread() -> None:
    """``--harden``: the calling thread as a helper of a real-time loop, each step on stderr;
    another thread of this process (--live, --can-log) holds the GIL 0.1 ms at most, not 5."""
    from hil.core.loop import REALTIME_SWITCH_INTERVAL_S
    from hil.core.realtime import Hardening, step_line

    sys.setswitchinterval(REALTIME_SWITCH_INTERVAL_S)
    for step in Hardening.for_helper().apply():
        print(step_line(step), file=sys.stderr, flush=True)


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


def _traced_handle(handle: Callable[[Any], None], trace: Any) -> Callable[[Any], None]:
    from hil.protocols.can_frames import from_message

    def traced(msg: Any) -> None:
        frame = from_message(msg)
        if frame is not None:
            trace.received(frame)
        handle(msg)

    return traced


def write_eds(emulator: Any, path: str) -> int:
    """``hil emulate drive --write-eds F``: the emulator's object dictionary as an EDS, its
    COB-IDs relative to the node id (``$NODEID+0x180``), its bit rates claimed."""
    from hil.emulators.drive.eds import write_eds as write_emulator_eds
    from hil.errors import UsageError

    try:
        write_emulator_eds(path, emulator.node_id, emulator.od_defaults())
    except OSError as exc:
        raise UsageError(f"--write-eds {path}: cannot write it: {exc.strerror}") from None
    print(f"hil: wrote the emulated drive's object dictionary (node {emulator.node_id}, "
          f"COB-IDs relative to $NODEID) to {path}", flush=True)
    return 0
