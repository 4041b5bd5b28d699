"""``hil drive scan`` (what is on the bus, read-only), ``hil drive sdo read|write`` (one
object by SDO), ``hil drive reset`` (clear a drive's FAULT), ``hil drive plan`` (whether N
axes fit one bus): the first commands on a new drive; ``hil drive home`` (a homing, HM) and
``hil drive move`` (a profile position move, PP), each a recorded run of its own."""

from __future__ import annotations

import argparse
import contextlib
import json
from typing import Any

from hil.cli.argtypes import node_id, output_file, positive_float, positive_int
from hil.cli.output import add_quiet_argument
from hil.core.registry import scheme_of

URL_HELP = ("the bus: socketcand://HOST:PORT[/CHANNEL] | INTERFACE://CHANNEL[?key=value&...] "
            "for any python-can interface (socketcan://can0, pcan://PCAN_USBBUS1, gs_usb://0, "
            "slcan:///dev/ttyACM0?bitrate=1000000, udp_multicast://239.0.0.1?port=43113...) | "
            "ethercat://IFACE[?slave=N] (an EtherCAT segment: the ethercat extra, a raw socket) "
            "| emulated")


def register(subparsers: argparse._SubParsersAction) -> None:
    drive = subparsers.add_parser("drive", help="CANopen drives on a bus: scan, fault reset, "
                                  "bus plan, homing, a profile move")
    sub = drive.add_subparsers(dest="drive_command", metavar="COMMAND", required=True)
    scan = sub.add_parser(
        "scan", help="list the nodes of a bus, their state and whether hil can drive them "
        "(read-only)",
        description="Read, without changing anything (SDO uploads only: no NMT, no SYNC, no "
        "write), what is on a CAN bus: with no --node, the nodes that answer an SDO read of "
        "0x1000; for each its NMT state (from its heartbeat), CiA 402 state (0x6041) and error "
        "code (0x603F, named), position (0x6064 in degrees, scaled by the drive's own 0x608F "
        "and 0x6091 as a run scales it), identity (0x1018), device type (0x1000), name "
        "(0x1008), error register and history (0x1001, 0x1003), supported modes by name "
        "(0x6502), the current PDO maps and heartbeat period; with --eds, the drive's EDS "
        "checked for every object hil reads, writes or maps; and a verdict: whether hil can "
        "drive it in the configured mode ([master] mode, with the config's stand-ins for "
        "objects it lacks and its [profile] and [homing]), and if not, every reason, one a "
        "line, the deciding one first (the modes it supports; a FAULT names its code and "
        "`hil drive reset`). Exit status 0: nodes found (with --eds: each can be driven); 1: "
        "none answered, or with --eds one cannot be driven.")
    scan.add_argument("url", metavar="URL", help=URL_HELP)
    scan.add_argument("--node", type=node_id, action="append",
                      help="inspect this node only (repeat for several)")
    scan.add_argument("--config", metavar="F.toml",
                      help="drive config laid over the default (its [master] mode, stand-ins "
                      "and [bus], [profile], [homing])")
    scan.add_argument("--eds", metavar="F.eds",
                      help="the drive's EDS or DCF: check every object hil reads, writes or "
                      "maps in the mode (exists, hil's size, readable, writable, "
                      "PDO-mappable as hil needs) and its vendor and product against 0x1018")
    scan.add_argument("--json", action="store_true", help="print the report as JSON")
    scan.set_defaults(handler=scan_command)
    _register_sdo(sub)
    reset = sub.add_parser(
        "reset", help="clear a drive's FAULT (CiA 402 fault reset)",
        description="Bring a drive left in FAULT to SWITCH ON DISABLED through the CiA 402 "
        "fault reset (disable voltage, then the rising edge of controlword bit 7), after its "
        "fault reaction has ended. A drive that is not in FAULT is left as it is; nothing is "
        "enabled.")
    reset.add_argument("url", metavar="URL", help=URL_HELP)
    reset.add_argument("--node", type=node_id, default=1, help="CANopen node id")
    reset.add_argument("--config", metavar="F.toml",
                       help="drive config laid over the default (hil/configs/drive.toml)")
    reset.set_defaults(handler=reset_command)
    plan = sub.add_parser(
        "plan", help="whether N axes fit one CAN bus at a cycle rate (no bus needed)",
        description="The bus time of one cycle with N axes on one bus - one SYNC, each "
        "axis' RPDO and TPDOs as the master maps them in its mode and TPDO layout, the "
        "drives' and the master's heartbeats - in its worst case (every frame with all the "
        "stuff bits it can take), which must not exceed the cycle period; where the limits are "
        "(the axes that fit this period, the shortest period for these axes) and, when it "
        "does not fit, the ways out, each as the setting that takes it. A run on several "
        "axes is held to the same figure. Exit status 0: it fits; 1: it does not.")
    plan.add_argument("--axes", type=positive_int, default=1, metavar="N",
                      help="axes on the bus (1)")
    plan.add_argument("--rate-hz", type=positive_float, metavar="HZ",
                      help="cycle rate (default: the config's master.cycle_period_us, 2000 Hz)")
    plan.add_argument("--bitrate", type=positive_int, metavar="BIT/S",
                      help="bus bitrate (default: the config's, 1000000); above 1000000 only "
                      "on a CAN FD bus (fd = true in the config's [bus.options])")
    plan.add_argument("--tpdo-layout", choices=("two", "one"),
                      help="the TPDOs per axis (default: the config's master.tpdo_layout, "
                      "two): two (6 + 6 bytes) or one (8 bytes, no velocity)")
    plan.add_argument("--config", metavar="F.toml",
                      help="drive config laid over the default: its [master] mode, "
                      "cycle_period_us, tpdo_layout, heartbeats, sync_echo and [bus] bitrate "
                      "and options")
    plan.add_argument("--json", action="store_true", help="print the plan as JSON")
    plan.set_defaults(handler=plan_command)
    _register_motions(sub)


#: the flags of ``hil drive move`` and ``hil drive home`` -> the motion setting each gives
#: (:data:`hil.servo.motion.MOTION_KEYS`)
MOTION_FLAGS = {"velocity": "velocity_deg_s", "acceleration": "acceleration_deg_s2",
                "deceleration": "deceleration_deg_s2", "method": "method",
                "offset": "offset_deg", "speed": "switch_speed_deg_s",
                "zero_speed": "zero_speed_deg_s",
                "homing_acceleration": "homing_acceleration_deg_s2"}


def _register_motions(sub: argparse._SubParsersAction) -> None:
    from hil.cli.recording import add_recording_arguments
    from hil.cli.units import degrees, degrees_per_s, degrees_per_s2, seconds
    from hil.cli.verdict import add_junit_argument

    run = ("A run like 'hil servo run' (lockstep by default, --realtime on the wall clock; the "
           "bus locked; the drive stopped, quick stop then disable voltage, at the end), "
           "recorded to an MCAP session: /drive/feedback every cycle (the profile as the drive "
           "ran it), /drive/motion (what each cycle sent), the profile objects as the drive "
           "holds them (metadata motion). [safety]'s position range and speed hold. Exit "
           "status 0 done, 2 refused, failed (the drive's error, the time-out) or stopped, 130 "
           "interrupted.")
    move = sub.add_parser(
        "move", help="move the axis to a position in profile position mode (PP)",
        description="Move the axis to TARGET (degrees of the axis, multi-turn, in the drive's "
        "frame: after 'hil drive home', from home) in CiA 402 profile position mode: the "
        "drive's own trapezoid with the profile velocity, acceleration and deceleration "
        "(0x6081, 0x6083, 0x6084: [profile], or these flags; left out, the drive's own), "
        "started by the new-set-point handshake (controlword bit 4, statusword bit 12) and "
        "done when the drive reports the target reached (statusword bit 10: within its "
        "position window 0x6067). A following error (statusword bit 13) or no target reached "
        "within [profile] timeout_s is an error. " + run)
    move.add_argument("url", metavar="URL", help=URL_HELP)
    move.add_argument("target", metavar="TARGET", type=degrees,
                      help="where to move [deg] (with --relative: by how much)")
    move.add_argument("--relative", action="store_true",
                      help="TARGET is a distance from where the axis stands")
    move.add_argument("--velocity", type=degrees_per_s, metavar="DEG_S",
                      help="profile velocity [deg/s] (0x6081; [profile] velocity_deg_s)")
    move.add_argument("--acceleration", type=degrees_per_s2, metavar="DEG_S2",
                      help="profile acceleration [deg/s^2] (0x6083)")
    move.add_argument("--deceleration", type=degrees_per_s2, metavar="DEG_S2",
                      help="profile deceleration [deg/s^2] (0x6084)")
    home = sub.add_parser(
        "home", help="home the axis (homing mode, HM)",
        description="Home the axis in CiA 402 homing mode: the method (0x6098: --method, "
        "[homing] method, else the drive's own), the home offset (0x607C: the position's value "
        "at home), the speeds (0x6099) and acceleration (0x609A), then controlword bit 4; done "
        "when the drive reports homing attained and the axis standing (statusword bits 12 and "
        "10). A homing error (statusword bit 13) or no home within [homing] timeout_s is an "
        "error; a drive whose method is 0 (none) is refused before it moves. " + run)
    home.add_argument("url", metavar="URL", help=URL_HELP)
    home.add_argument("--method", type=int, metavar="N",
                      help="the CiA 402 homing method (0x6098; [homing] method): 1, 2 a limit "
                      "switch and the index pulse, 17, 18 a limit switch, 33, 34 the index "
                      "pulse, 35, 37 where the axis stands...")
    home.add_argument("--offset", type=degrees, metavar="DEG",
                      help="the position's value at home [deg] (0x607C; [homing] offset_deg)")
    home.add_argument("--speed", type=degrees_per_s, metavar="DEG_S",
                      help="speed while searching for the switch [deg/s] (0x6099:1)")
    home.add_argument("--zero-speed", type=degrees_per_s, metavar="DEG_S",
                      help="speed while searching for zero [deg/s] (0x6099:2)")
    home.add_argument("--homing-acceleration", type=degrees_per_s2, metavar="DEG_S2",
                      help="homing acceleration [deg/s^2] (0x609A)")
    for parser, table in ((move, "profile"), (home, "homing")):
        parser.add_argument("--timeout", type=seconds, metavar="S",
                            help=f"how long it may take [s] ([{table}] timeout_s)")
        parser.add_argument("--node", type=positive_int, help="CANopen node id (default: "
                            "[master] node_id, 1)")
        parser.add_argument("--config", metavar="F.toml",
                            help="drive config laid over the default (hil/configs/drive.toml)")
        parser.add_argument("--eds", metavar="F.eds", help="the drive's EDS or DCF, checked "
                            "for every object the mode uses before anything is written")
        parser.add_argument("--reset-fault", action="store_true",
                            help="clear a drive left in FAULT before enabling it")
        parser.add_argument("--realtime", action="store_true",
                            help="follow the wall clock (default: lockstep virtual time)")
        add_quiet_argument(parser)
        parser.add_argument("--out", metavar="F.mcap", type=output_file, help="session file "
                            "(default: sessions/motion-move|home-DATE-TIME.mcap)")
        parser.add_argument("--json", action="store_true", help="print the KPIs as JSON")
        add_junit_argument(parser)
        add_recording_arguments(parser)
        parser.set_defaults(handler=motion_command, motion=parser.prog.split()[-1])


def motion_command(args: argparse.Namespace) -> int:
    """``hil drive move`` / ``hil drive home``: the motion as a run, its report."""
    from hil.cli.recording import recording_options
    from hil.cli.verdict import finish
    from hil.servo.motion import MOTION_KEYS, MotionOptions, run_motion_options

    def options() -> MotionOptions:
        flags = vars(args)
        keys = {MOTION_KEYS[setting]: (flags[flag], "--" + flag.replace("_", "-"))
                for flag, setting in MOTION_FLAGS.items() if flags.get(flag) is not None}
        if args.timeout is not None:
            table = "profile" if args.motion == "move" else "homing"
            keys[f"{table}.timeout_s"] = (args.timeout, "--timeout")
        return MotionOptions(args.motion, getattr(args, "target", None),
                             getattr(args, "relative", False), keys, drive=args.url,
                             node=args.node, drive_config=args.config, eds=args.eds,
                             realtime=args.realtime, out=args.out, quiet=args.quiet,
                             reset_fault=args.reset_fault, recording=recording_options(args))

    return finish(args, f"hil drive {args.motion}", options, run_motion_options,
                  lambda made, kpis: format_motion(kpis))


def format_motion(kpis: dict[str, Any]) -> str:
    """The human summary of ``hil drive move`` / ``hil drive home``."""
    if kpis["motion"] == "move":
        what = (f"PP move to {kpis['target_deg']:.3f} deg: at {kpis['position_deg']:.3f} deg "
                f"(error {kpis['error_deg']:+.4f} deg)")
    else:
        what = f"homed (method {kpis['method']}): at {kpis['position_deg']:.3f} deg"
    return "\n".join([
        f"drive {kpis['drive']}: {what} after {kpis['time_s']:.3f} s, clock {kpis['clock']}",
        f"  peak velocity {kpis['peak_velocity_deg_s']:.1f} deg/s, peak current "
        f"{kpis['peak_current_mA']:.0f} mA, ticks {kpis['ticks']} in {kpis['wall_s']:.2f} s "
        "wall",
        f"  session {kpis['mcap']}"])


def _register_sdo(sub: argparse._SubParsersAction) -> None:
    sdo = sub.add_parser(
        "sdo", help="read or write one object of a drive by SDO",
        description="Read or write one object of a drive by SDO, typed by the drive's EDS "
        "(--eds) or by --type (which wins). A read without a type prints the bytes and, for "
        "1, 2, 4 or 8 bytes, the unsigned value. A write sends 1, 2 or 4 bytes (an expedited "
        "download) and is refused when a valid PDO carries the object while the drive is "
        "operational (NMT OPERATIONAL by its heartbeat, or OPERATION ENABLED by 0x6041). An "
        "SDO abort is one line with its CiA 301 code and text (exit 2). Takes the bus lock, "
        "as a run does.")
    ops = sdo.add_subparsers(dest="sdo_command", metavar="read|write", required=True)
    read = ops.add_parser(
        "read", help="upload one object",
        description="Upload one object (nothing is written) and print it as its type says "
        "(--type, else the EDS's); without a type, its bytes and, for 1, 2, 4 or 8 of them, "
        "the unsigned value.")
    write = ops.add_parser(
        "write", help="download one value to one object",
        description="Download one value (1, 2 or 4 bytes: an expedited SDO download) to one "
        "object, encoded as its type says (--type, else the EDS's). Refused in one line when "
        "a valid PDO carries the object while the drive is operational (NMT OPERATIONAL by "
        "its heartbeat, or OPERATION ENABLED by 0x6041).")
    for parser in (read, write):
        parser.add_argument("url", metavar="URL", help=URL_HELP)
        parser.add_argument("object", metavar="INDEX[:SUB]", type=_object,
                            help="the object: INDEX in hex (0x6041 or 6041), SUB decimal or "
                            "0x-hex (default 0), e.g. 0x1018:1")
    write.add_argument("value", metavar="VALUE",
                       help="the value: an integer (decimal, 0x-hex, negative), a number for "
                       "REAL32, 0/1/true/false for BOOLEAN")
    for parser in (read, write):
        parser.add_argument("--node", type=node_id, default=1,
                            help="CANopen node id (1)")
        parser.add_argument("--type", type=_data_type, metavar="T",
                            help="the object's data type: u8, u16, u32, u64, i8, i16, i32, "
                            "i64, f32, f64, bool, str, or the CiA 301 names BOOLEAN, "
                            "INTEGER8..64, UNSIGNED8..64, REAL32, REAL64, VISIBLE_STRING, "
                            "OCTET_STRING (any case)")
        parser.add_argument("--eds", metavar="F.eds",
                            help="the drive's EDS or DCF, for the object's data type")
    read.add_argument("--json", action="store_true",
                      help="print node, object, index, subindex, type, size, hex, value")
    read.set_defaults(handler=sdo_read_command)
    write.set_defaults(handler=sdo_write_command)


def _object(text: str) -> tuple[int, int]:
    from hil.drivers.canopen.sdo_tool import parse_object

    try:
        return parse_object(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _data_type(text: str) -> int:
    from hil.drivers.canopen.sdo_tool import parse_type

    try:
        return parse_type(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _sdo_type(args: argparse.Namespace) -> int | None:
    """The object's data type: --type, else the EDS's, else None."""
    from hil.drivers.canopen.sdo_tool import eds_type

    if args.type is not None:
        return int(args.type)
    if args.eds:
        return eds_type(args.eds, args.node, *args.object)
    return None


def _sdo_client(master: Any) -> Any:
    """An SDO client of the master's node on its bus that ignores every other frame (the tool
    runs no cyclic exchange to hand them to); on EtherCAT the master's CoE channel."""
    from hil.drivers.canopen.sdo import SdoClient

    if scheme_of(master.url) == "ethercat":
        return master.sdo

    return SdoClient(master.link, master.node_id, master.config.sdo_timeout_s,
                     lambda frame: None)


def sdo_read_command(args: argparse.Namespace) -> int:
    from hil.drivers.canopen.sdo_tool import read_object

    data_type = _sdo_type(args)
    index, subindex = args.object
    with _bus_lock(args.url):
        master = _master(args.url, None, args.node)
        try:
            value = read_object(_sdo_client(master), index, subindex, data_type)
        finally:
            master.disconnect()
    print(json.dumps(value.as_dict()) if args.json else value.describe())
    return 0


def sdo_write_command(args: argparse.Namespace) -> int:
    from hil.drivers.canopen.sdo_tool import (
        TYPE_NAMES,
        download_format,
        encode,
        object_name,
        write_object,
    )
    from hil.errors import UsageError

    data_type = _sdo_type(args)
    if data_type is None:
        raise UsageError("hil drive sdo write needs the object's type: --type T or --eds F.eds")
    raw = encode(args.value, data_type)
    download_format(raw)  # a value too long is said before the bus is touched
    index, subindex = args.object
    with _bus_lock(args.url):
        master = _master(args.url, None, args.node)
        try:
            if scheme_of(args.url) == "ethercat":  # SAFE-OP and OP come with a run only
                master.sdo.download(index, subindex, raw)
            else:
                write_object(master.link, _sdo_client(master), index, subindex, raw)
        finally:
            master.disconnect()
    print(f"node {args.node} {object_name(*args.object)} {TYPE_NAMES[data_type]} = "
          f"{args.value}: written")
    return 0


def _drive_config(config: str | None, node: int | None) -> Any:
    from hil.servo.config import load_drive_config

    overrides = {"master": {"node_id": node}} if node else {}
    return load_drive_config(config, overrides=overrides)


def _master(url: str, config: str | None, node: int | None) -> Any:
    from hil.servo.rig import open_drive

    return open_drive(url, _drive_config(config, node))


def _scan_segment(url: str, positions: list[int] | None, mode: str, eds: str | None,
                  config: Any) -> list[Any]:
    """The slaves of an EtherCAT segment (``--node N``: slave positions)."""
    from hil.drivers.ethercat.scan import scan_segment
    from hil.drivers.ethercat.segment import Segment
    from hil.servo.ethercat import parse_ethercat_url

    iface, slave = parse_ethercat_url(url)
    segment = Segment(iface, url.partition("?")[0])
    try:
        return scan_segment(segment, positions or ([slave] if slave else None), mode, eds,
                            config)
    finally:
        segment.close()


def _bus_lock(url: str) -> contextlib.AbstractContextManager[Any]:
    """The bus locked for this command, as a run locks it (an emulated drive is our own)."""
    from hil.core.device_lock import lock_device
    from hil.servo.axes import bus_lock_key

    return contextlib.nullcontext() if url == "emulated" else \
        lock_device(bus_lock_key(url), "drive bus")


def scan_command(args: argparse.Namespace) -> int:
    from hil.drivers.canopen.eds import import_description
    from hil.drivers.canopen.scan import scan

    if args.eds:  # an unreadable file is said before the bus is touched
        import_description(args.eds, args.node[0] if args.node else 1)
    with _bus_lock(args.url):
        if scheme_of(args.url) == "ethercat":
            config = _drive_config(args.config, None).master
            reports = _scan_segment(args.url, args.node, config.mode, args.eds, config)
        else:
            master = _master(args.url, args.config, None)
            config = master.config
            try:
                reports = scan(master.link, args.node, config.mode, args.eds, config)
            finally:
                master.disconnect()
    if args.json:
        print(json.dumps({"url": args.url, "mode": config.mode,
                          "nodes": [r.as_dict() for r in reports]}, indent=2))
    else:
        print(format_scan(args.url, config.mode, reports))
    # a drive checked against its description that cannot be driven fails the scan
    return 0 if reports and (not args.eds or all(r.drivable for r in reports)) else 1


def format_scan(url: str, mode: str, reports: list[Any]) -> str:
    if not reports:
        return f"{url}: no node answered"
    lines = [f"{url}: {len(reports)} node(s), checked for {mode.upper()}"]
    for r in reports:
        identity = ", ".join(f"{k} 0x{v:X}" for k, v in r.identity.items()) or "-"
        device = f"0x{r.device_type:08X}" if r.device_type is not None else "-"
        modes = "-" if r.supported_modes is None else \
            f"{', '.join(r.modes) or 'none'} (0x6502 = 0x{r.supported_modes:08X})"
        lines += [
            f"node {r.node_id}: {r.device_name or 'unnamed'}, "
            f"{r.nmt_state if r.nmt_state.startswith('AL ') else 'NMT ' + r.nmt_state}",
            f"  CiA 402 state {_state(r)}, error code {r.error_text or '-'}",
            f"  position {_position(r)}",
            f"  device type {device}, identity {identity}",
            f"  error register {'-' if r.error_register is None else hex(r.error_register)}, "
            f"history {', '.join(r.error_history) or 'empty'}",
            f"  supported modes {modes}, heartbeat "
            f"{'-' if r.heartbeat_ms is None else str(r.heartbeat_ms) + ' ms'}",
        ]
        for pdo in r.pdos:
            mapped = ", ".join(pdo.mapped) or "nothing mapped"
            if pdo.cob_id:  # a CAN PDO
                lines.append(f"  {pdo.name} 0x{pdo.cob_id:03X} "
                             f"{'valid' if pdo.valid else 'off'}, type {pdo.transmission}: "
                             f"{mapped}")
            else:  # an EtherCAT PDO, as its SyncManager's assignment lists it
                lines.append(f"  {pdo.name}: {mapped}")
        if r.eds is not None:
            problems = r.eds["problems"]
            lines.append(f"  EDS {r.eds['path']}: " + (
                f"{len(problems)} problem(s), below" if problems else
                "every object hil reads, writes or maps is there as hil needs it"))
        lines += _verdict_lines(r)
    return "\n".join(lines)


def _verdict_lines(report: Any) -> list[str]:
    """``can drive: yes, in CSP`` (and its notes), or ``can drive: no, `` and every reason,
    one a line, the deciding one first."""
    if report.drivable:
        return [f"  can drive: yes, in {report.mode.upper()}",
                *(f"    {note}" for note in report.notes)]
    first, *rest = report.problems
    return [f"  can drive: no, {first}", *(f"    {problem}" for problem in rest)]


def _state(report: Any) -> str:
    if report.state is None:
        return "-"
    return f"{report.state} (statusword 0x{report.statusword:04X})"


def _position(report: Any) -> str:
    if report.position_deg is None:
        return "-"
    s = report.scaling
    gear = f"gear {s['motor_revolutions']}:{s['shaft_revolutions']}"
    return (f"{report.position_deg:.3f} deg (0x6064 = {report.position_counts} counts, "
            f"{s['counts_per_turn']} per turn: 0x608F {s['increments_per_rev']} "
            f"increments/rev, {gear})")


def reset_command(args: argparse.Namespace) -> int:
    from hil.protocols.cia402 import state_of

    with _bus_lock(args.url):
        master = _master(args.url, args.config, args.node)
        try:
            before = state_of(master.states.reach())
            master.fault_reset()
            after = state_of(master.states.statusword())
        finally:
            master.disconnect()
    if before == after:
        print(f"drive node {master.node_id}: {after}, nothing to reset")
    else:
        print(f"drive node {master.node_id}: {before} -> {after}")
    return 0


def plan_command(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from hil.drivers.canopen.bus_plan import plan_axes
    from hil.errors import UsageError
    from hil.servo.config import check_bitrate, load_drive_config

    drive = load_drive_config(args.config)
    master = drive.master
    if args.rate_hz:
        master = replace(master, cycle_period_s=1.0 / args.rate_hz)
    if args.bitrate:
        fd = bool(drive.bus is not None and drive.bus.options.get("fd"))
        check_bitrate(args.bitrate, fd, "--bitrate")
        master = replace(master, bitrate=args.bitrate)
    if args.tpdo_layout:
        master = replace(master, tpdo_layout=args.tpdo_layout)
        if args.tpdo_layout == "one" and master.sync_echo is not None:
            raise UsageError("--tpdo-layout one fills its 8 bytes: no room for the config's "
                             "master.sync_echo (set it to \"\")")
    plan = plan_axes(master, [f"axis {i}" for i in range(1, args.axes + 1)])
    if args.json:
        print(json.dumps({"mode": master.mode, "tpdo_layout": master.tpdo_layout,
                          **plan.summary()}, indent=2))
    else:
        print(format_plan(master.mode, plan))
    return 0 if plan.fits else 1


def format_plan(mode: str, plan: Any) -> str:
    from hil.drivers.can_bus_time import WORST_CASE

    b = plan.budget
    axis = plan.axes[0]
    tpdos = " + ".join(str(n) for n in axis.tpdo_bytes)
    lines = [
        f"{len(plan.axes)} {'axis' if len(plan.axes) == 1 else 'axes'} in {mode.upper()} on "
        f"one bus at {b.bitrate} bit/s, "
        f"cycle {b.period_us:.0f} us ({1e6 / b.period_us:.0f} Hz): one SYNC, per axis an "
        f"RPDO of {axis.rpdo_bytes} bytes and {'TPDOs' if len(axis.tpdo_bytes) > 1 else 'a TPDO'}"
        f" of {tpdos} bytes, heartbeats",
        f"  bus time per cycle {plan.bus_time_us:.0f} us ({WORST_CASE}): "
        f"{100 * b.load_worst:.0f} % of the period, which it must not exceed",
        f"  at this period at most {plan.max_axes} such "
        f"{'axis fits' if plan.max_axes == 1 else 'axes fit'}; these fit from "
        f"{plan.min_period_us:.0f} us ({1e6 / plan.min_period_us:.0f} Hz) on",
        "  fits" if plan.fits else f"  does not fit: {plan.problem()}",
    ]
    return "\n".join(lines)
