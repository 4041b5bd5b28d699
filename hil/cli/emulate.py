"""``hil emulate bench|drive|line``: the flags of a standalone emulator process, and what it
prints; :mod:`hil.emulation` serves the emulator."""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from hil.cli.argtypes import host_port, positive_int
from hil.cli.recording import add_live_arguments, live_address
from hil.core.config import load_toml
from hil.core.exposure import exposure
from hil.core.lifeline import die_with_parent
from hil.core.notice import warn
from hil.core.recording.live import announce, live_exposure
from hil.emulation import (
    BENCH_LIVE_HZ,
    DRIVE_LIVE_HZ,
    harden_serving_thread,
    serve_bench,
    serve_drives,
    serve_until_stopped,
    until_stopped,
)
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

#: where a hardened emulator serves that does not answer within the loop's tick
APART = "SCHED_FIFO below hil's loop, a core apart from the loop's"

if TYPE_CHECKING:
    from hil.core.realtime import Step


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
    _add_harden_argument(eb, APART)
    _add_fault_arguments(eb, "bench", "delay@2-4:ms=300, drop@5-8, weld@3:relay=P1")
    add_live_arguments(eb, rates=False, tuning=False)
    eb.set_defaults(handler=emulate_bench_command)
    ed = emu_sub.add_parser("drive", help="CiA 402 servo drive over socketcand or EtherCAT")
    ed.add_argument("--socketcand", type=host_port, metavar="HOST:PORT",
                    help="serve the socketcand protocol here (port 0: any free port, printed)")
    ed.add_argument("--ethercat", metavar="IFACE",
                    help="answer EtherCAT frames on this network interface instead (a veth "
                    "end, a NIC of its own; raw socket: root or CAP_NET_RAW): one slave per "
                    "--node, in that order, CiA 402 over CoE; a master reaches them with "
                    "ethercat://OTHER-END?slave=N")
    ed.add_argument("--esi", metavar="F.xml",
                    help="with --ethercat: a vendor's ESI file the slaves' SII EEPROM is built "
                    "from (identity, name, mailbox, SyncManagers, default PDOs; default: "
                    "hil's, from the drive's dictionary); where it has a <Dictionary> and "
                    "no --eds is given, its CoE objects are the twin's too, as --eds F "
                    "would make them (--set gives what it leaves empty)")
    ed.add_argument("--write-eds", metavar="F.eds",
                    help="write the emulated drive's object dictionary as an EDS file (for "
                    "canopen's import_od, CANopen tools, `[master] eds`) and exit")
    ed.add_argument("--eds", metavar="F.eds",
                    help="a twin of your drive: its EDS or DCF (canopen's import_od) is the "
                    "emulated drive's dictionary, PDO maps, scaling, modes and identity "
                    "(default: emulator.eds); what it cannot emulate is one line on stderr "
                    "and answered with an SDO abort; without --socketcand: print what the "
                    "twin takes and refuses, and exit")
    ed.add_argument("--set", action="append", type=object_value, default=[],
                    metavar="INDEX:SUB=VALUE",
                    help="an object's power-on value, e.g. 0x6075:0=2000 (repeatable; over "
                    "emulator.set): a value the EDS leaves empty for commissioning (a DCF's "
                    "ParameterValue gives it too), or a unit the file lacks (0x608F:1), "
                    "which the twin keeps hidden as the drive has none")
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
    ed.add_argument("--model", metavar="F.json",
                    help="the axis as a model file (`hil identify` writes them): one input, a "
                    "current in mA, one output, a position in deg, its period dividing "
                    "master.cycle_period_us (default: emulator.model, else the published axis)")
    _add_harden_argument(ed, "while the drives keep their own clock (not a lockstep "
                         "master's): over socketcand SCHED_FIFO above hil's loop, on the "
                         "loop's core (each SYNC answered within the loop's tick); as EtherCAT "
                         f"slaves {APART}")
    ed.add_argument("--clock", choices=CLOCKS, default="auto",
                    help="the drives' time: auto (default: their own wall clock, until a "
                    "lockstep master asks for its SYNC time, as `hil servo run` does, and "
                    "again when it lets go or stays silent for longer than it said), sync (the "
                    "SYNCs' time from power-on: time passes only when SYNCs come), wall (their "
                    "own clock always: a lockstep master is told so and watches them on the "
                    "wall clock)")
    _add_fault_arguments(ed, "drive", "emcy@2:code=0x2310, no_heartbeat@1-3")
    add_live_arguments(ed, rates=False, tuning=False)
    ed.set_defaults(handler=emulate_drive_command)
    el = emu_sub.add_parser(
        "line", help="a serial line (a null-modem cable between two pseudo-terminals), noisy "
        "on request: a master on one end, e.g. hil bench run --bench modbus-rtu://END, and "
        "hil emulate bench --serial OTHER-END on the other")
    el.add_argument("--baud", type=positive_int,
                    help="deliver the bytes at this baud rate, 10 bits a byte (default: as fast "
                    "as the kernel copies them)")
    _add_fault_arguments(el, "line", "noise@5-10:rate=0.02,seed=1")
    el.set_defaults(handler=emulate_line_command)


def _add_harden_argument(parser: argparse.ArgumentParser, how: str) -> None:
    parser.add_argument("--harden", action=argparse.BooleanOptionalAction, default=True,
                        help=f"serve as a real-time process where the OS allows (default; as "
                        f"`hil doctor` reports), {how}, locked memory; each step granted or "
                        "refused is printed on stderr as 'hil: real-time: STEP granted|"
                        "refused: ...', and a warning names those refused. --no-harden: an "
                        "ordinary process")


def say_hardening(steps: list[Step], emulator: str) -> None:
    """Each hardening step on stderr (``hil: real-time: STEP granted|refused: ...``), then,
    when the machine refused any, one warning naming them."""
    from hil.core.realtime import step_line

    for step in steps:
        print(step_line(step), file=sys.stderr, flush=True)
    refused = [step.name for step in steps if not step.granted]
    if refused:
        warn(f"the {emulator} emulator serves without {', '.join(refused)} (refused, above): "
             "a real-time master may find its answers late; `hil doctor` says what this "
             "machine grants and what would change it")


def object_value(text: str) -> tuple[str, int]:
    """``--set 0x6075:0=2000`` -> ("0x6075:0", 2000) (argparse: one line naming the
    problem)."""
    name, equals, value = text.partition("=")
    try:
        number = int(value, 0)
    except ValueError:
        number = None
    if not equals or number is None or ":" not in name:
        raise argparse.ArgumentTypeError(f"give INDEX:SUB=VALUE, e.g. 0x6075:0=2000, got {text!r}")
    return name.strip(), number


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


def emulate_bench_command(args: argparse.Namespace) -> int:
    """Serve the bench plant until Ctrl-C or SIGTERM, on the wall clock or a lockstep master's
    time (``--clock``); a master taking or letting go of the time is a line on stderr."""
    die_with_parent()
    from hil.bench.config import load_bench_config
    from hil.core.realtime import Hardening

    config = load_bench_config(args.config)
    config = replace(config, faults=tuple(faults_of(args, "bench", config.faults)))
    hardening = Hardening.for_helper() if args.harden else None
    # before its threads start (they take the same scheduling); said once it listens
    steps = harden_serving_thread(hardening) if hardening is not None else []
    try:
        bench = serve_bench(
            config.emulating(args.seed, args.disturbance or None), tcp=args.tcp,
            serial=args.serial, baudrate=args.baud, parity=args.parity, stopbits=args.stopbits,
            clock=args.clock, on_fault=print_event,
            on_clock=lambda line: print(f"hil: clock: {line}", file=sys.stderr, flush=True))
    except BaseException:  # a port it cannot listen on: the caller's thread as it was
        if hardening is not None:
            hardening.restore()
        raise
    if steps:
        say_hardening(steps, "bench")
    units = bench.emulator.devices.units

    def ready(live_url: str | None) -> None:
        _print_live(live_url, args)
        if args.tcp is not None:
            _warn_exposed(f"the bench emulator on {bench.url}", args.tcp[0],
                          "read the emulated bench and switch its relays")
        print(f"hil: bench emulator listening on {bench.url} (relays unit {units['relays']}, "
              f"meter unit {units['meter']}, levels unit {units['levels']}); Ctrl-C stops",
              flush=True)

    def stopped() -> None:
        print(f"hil: bench emulator stopped after {time.monotonic() - bench.started:.1f} s "
              f"(plant time {bench.emulator.plant.t_s:.2f} s)", flush=True)

    serve_until_stopped(bench, live_address(args), BENCH_LIVE_HZ, ready, stopped)
    return 0


def emulate_drive_command(args: argparse.Namespace) -> int:
    """Serve the emulated CiA 402 drive over socketcand in real time until Ctrl-C or SIGTERM."""
    die_with_parent()
    from hil.core.settings import Layer, lay
    from hil.errors import UsageError
    from hil.servo.config import SOURCE, drive_layers, parse_drive_config

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
    layers, text = drive_layers(args.config)
    layers.append(Layer("overrides", {"emulator": overrides}))
    # the flags' paths from the working folder; their errors name them
    for flag, key, path in (("--model", "model", args.model), ("--eds", "eds", args.eds)):
        if path is not None:
            layers.append(Layer(flag, {"emulator": {key: path}}))
    if args.esi is not None and args.eds is None and _esi_has_objects(args.esi):
        layers.append(Layer("--esi", {"emulator": {"eds": args.esi}}))
    if args.set:
        layers.append(Layer("--set", {"emulator": {"set": dict(args.set)}}))
    emulator = parse_drive_config(lay(layers), args.config or SOURCE, text).emulator
    if args.write_eds:
        if emulator.eds is not None:
            raise UsageError(f"--write-eds writes hil's own dictionary; the twin's is "
                             f"{emulator.eds} (--eds, emulator.eds) already")
        return write_eds(emulator, args.write_eds)
    if emulator.eds is not None and not twin_report(
            emulator, args.socketcand is None and args.ethercat is None):
        return 0
    if args.ethercat is not None:
        if args.socketcand is not None or args.can_log:
            raise UsageError("--ethercat serves EtherCAT frames: no --socketcand or --can-log "
                             "beside it")
        return _serve_ethercat(args, emulator, nodes_ids)
    if args.esi is not None:
        raise UsageError("--esi builds an EtherCAT slave's SII: it needs --ethercat IFACE")
    if args.socketcand is None:
        raise UsageError("hil emulate drive needs --socketcand HOST:PORT or --ethercat IFACE "
                         "(or --write-eds F)")
    drives = serve_drives(emulator, nodes_ids, *args.socketcand, clock=args.clock,
                          faults=faults_of(args, "drive", emulator.faults), can_log=args.can_log,
                          on_fault=print_event)
    nodes = drives.nodes
    bound_host, bound_port = drives.server.address
    ids = ", ".join(str(node.node_id) for node in nodes)

    def ready(live_url: str | None) -> None:
        _print_live(live_url, args)
        _warn_exposed(f"the drive emulator on socketcand://{bound_host}:{bound_port}",
                      args.socketcand[0],
                      "send CAN frames to the emulated drives")
        if args.harden:  # the serving thread only, reported before the ready line
            say_hardening(drives.harden(), "drive")
        print(f"hil: drive emulator node{'s' if len(nodes) > 1 else ''} {ids} on socketcand "
              f"{bound_host}:{bound_port} (bus {emulator.channel}, clock {args.clock}); "
              "Ctrl-C stops", flush=True)

    def stopped() -> None:
        print(f"hil: drive emulator stopped after {nodes[0].sync_count} SYNC "
              f"(plant time {nodes[0].plant.time_s:.3f} s)", flush=True)

    serve_until_stopped(drives, live_address(args), DRIVE_LIVE_HZ, ready, stopped)
    return 0


def _serve_ethercat(args: argparse.Namespace, emulator: Any, nodes_ids: list[int]) -> int:
    """``--ethercat IFACE``: the drives as a line of EtherCAT slaves until Ctrl-C or SIGTERM."""
    from hil.emulation import serve_ethercat_drives
    from hil.errors import UsageError

    try:
        drives = serve_ethercat_drives(emulator, nodes_ids, args.ethercat, clock=args.clock,
                                       faults=faults_of(args, "drive", emulator.faults),
                                       on_fault=print_event, esi=args.esi)
    except PermissionError:
        raise UsageError(f"--ethercat {args.ethercat}: a raw socket needs root or "
                         "CAP_NET_RAW") from None
    except OSError as exc:
        raise UsageError(f"--ethercat {args.ethercat}: cannot open the interface "
                         f"({exc.strerror or exc})") from None
    nodes = drives.nodes
    ids = ", ".join(str(node.node_id) for node in nodes)

    def ready(live_url: str | None) -> None:
        _print_live(live_url, args)
        if args.harden:
            say_hardening(harden_serving_thread(), "drive")
        print(f"hil: drive emulator node{'s' if len(nodes) > 1 else ''} {ids} as EtherCAT "
              f"slave{'s' if len(nodes) > 1 else ''} 1..{len(nodes)} on {args.ethercat} "
              f"(clock {args.clock}); Ctrl-C stops", flush=True)

    def stopped() -> None:
        print(f"hil: drive emulator stopped after {drives.segment.frames} EtherCAT frames, "
              f"{nodes[0].sync_count} cycles (plant time {nodes[0].plant.time_s:.3f} s)",
              flush=True)

    serve_until_stopped(drives, live_address(args), DRIVE_LIVE_HZ, ready, stopped)
    return 0


def emulate_line_command(args: argparse.Namespace) -> int:
    """Carry the bytes between the line's two ends until Ctrl-C or SIGTERM, playing its faults
    (seconds since it started); what it carried and flipped each way is the last line."""
    die_with_parent()
    from hil.emulators.null_modem import NullModem

    faults = faults_of(args, "line")
    with until_stopped() as stop, NullModem(args.baud, faults=faults,
                                            on_fault=print_event) as line:
        started = time.monotonic()
        print(f"hil: line {line.ports[0]} <-> {line.ports[1]}; Ctrl-C stops", flush=True)
        while not stop.wait(0.2):
            pass
    ways = (f"{line.ports[0]} -> {line.ports[1]}", f"{line.ports[1]} -> {line.ports[0]}")
    print(f"hil: line stopped after {time.monotonic() - started:.1f} s: " + "; ".join(
        f"{way} {carried} bytes, {flipped} flipped"
        for way, carried, flipped in zip(ways, line.carried, line.flipped, strict=True)),
        flush=True)
    return 0


def _print_live(live_url: str | None, args: argparse.Namespace) -> None:
    """The emulator's live view (``--live``), if any: its URL, and a warning beyond loopback."""
    if live_url is not None:
        announce(live_url, live_exposure(live_url, args.live[0]))


def _warn_exposed(server: str, host: str, reach: str) -> None:
    """One line on stderr when ``server`` listens on ``host`` beyond loopback."""
    warning = exposure(server, host, reach)
    if warning is not None:
        warn(warning)


def _esi_has_objects(path: str) -> bool:
    """Whether the ESI file at ``path`` describes its CoE objects (a ``<Dictionary>``): then
    it is the twin's dictionary too, as an EDS is with --eds."""
    from hil.emulators.ethercat.esi_dictionary import esi_dictionary

    return esi_dictionary(path) is not None


def twin_report(emulator: Any, full: bool) -> bool:
    """The twin of ``emulator.eds`` built once (a file it cannot be a twin of: one line):
    its summary on stderr before serving, or (``full``) on stdout with every object it does
    not emulate, one a line. Whether to serve it."""
    from hil.emulators.drive.twin import eds_twin

    twin = eds_twin(emulator.eds, emulator)
    if not full:
        print(f"hil: {twin.summary(emulator.node_id)}", file=sys.stderr, flush=True)
        return True
    print("\n".join([twin.summary(emulator.node_id), *twin.report()]), flush=True)
    return False


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
