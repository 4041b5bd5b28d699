"""``hil drive scan`` (what is on the bus, read-only), ``hil drive reset`` (clear a drive's
FAULT) and ``hil drive plan`` (whether N axes fit one bus): the first commands on a new drive."""

from __future__ import annotations

import argparse
import contextlib
import json
from typing import Any

from hil.cli.argtypes import positive_float, positive_int

URL_HELP = ("the bus: socketcand://HOST:PORT[/CHANNEL] | INTERFACE://CHANNEL[?key=value&...] "
            "for any python-can interface (socketcan://can0, pcan://PCAN_USBBUS1, gs_usb://0, "
            "slcan:///dev/ttyACM0?bitrate=1000000, udp_multicast://239.0.0.1?port=43113...) | "
            "emulated")


def register(subparsers: argparse._SubParsersAction) -> None:
    drive = subparsers.add_parser("drive", help="CANopen drives on a bus: scan, fault reset, "
                                  "bus plan")
    sub = drive.add_subparsers(dest="drive_command", metavar="COMMAND", required=True)
    scan = sub.add_parser(
        "scan", help="list the nodes of a bus and what hil can drive (read-only)",
        description="Read, without changing anything (SDO uploads only: no NMT, no SYNC, no "
        "write), what is on a CAN bus: with no --node, the nodes that answer an SDO read of "
        "0x1000; for each its NMT state (from its heartbeat), identity (0x1018), device type "
        "(0x1000), name (0x1008), error register and history (0x1001, 0x1003), supported "
        "modes (0x6502), the current PDO maps and heartbeat period, and whether hil can drive "
        "it in the configured mode, and if not, why.")
    scan.add_argument("url", metavar="URL", help=URL_HELP)
    scan.add_argument("--node", type=positive_int, action="append",
                      help="inspect this node only (repeat for several)")
    scan.add_argument("--config", metavar="F.toml",
                      help="drive config laid over the default (its [master] mode and [bus])")
    scan.add_argument("--json", action="store_true", help="print the report as JSON")
    scan.set_defaults(handler=scan_command)
    reset = sub.add_parser(
        "reset", help="clear a drive's FAULT (CiA 402 fault reset)",
        description="Bring a drive left in FAULT to SWITCH ON DISABLED through the CiA 402 "
        "fault reset (disable voltage, then the rising edge of controlword bit 7), after its "
        "fault reaction has ended. A drive that is not in FAULT is left as it is; nothing is "
        "enabled.")
    reset.add_argument("url", metavar="URL", help=URL_HELP)
    reset.add_argument("--node", type=positive_int, default=1, help="CANopen node id")
    reset.add_argument("--config", metavar="F.toml",
                       help="drive config laid over the default (hil/configs/drive.toml)")
    reset.set_defaults(handler=reset_command)
    plan = sub.add_parser(
        "plan", help="whether N axes fit one CAN bus at a cycle rate (no bus needed)",
        description="The bus time of one cycle with N axes on one bus - one SYNC, each "
        "axis' RPDO and TPDOs as the master maps them in its mode, the drives' and the "
        "master's heartbeats - with worst-case bit stuffing, against the cycle period; where "
        "the limits are (the axes that fit this period, the shortest period for these axes) "
        "and, when it does not fit, the ways out. Exit status 0: it fits; 1: it does not.")
    plan.add_argument("--axes", type=positive_int, default=1, metavar="N",
                      help="axes on the bus (1)")
    plan.add_argument("--rate-hz", type=positive_float, metavar="HZ",
                      help="cycle rate (default: the config's cycle period, 2000 Hz)")
    plan.add_argument("--bitrate", type=positive_int, metavar="BIT/S",
                      help="bus bitrate (default: the config's, 1000000)")
    plan.add_argument("--config", metavar="F.toml",
                      help="drive config laid over the default: its [master] mode, heartbeats, "
                      "sync_echo and [bus] bitrate")
    plan.add_argument("--json", action="store_true", help="print the plan as JSON")
    plan.set_defaults(handler=plan_command)


def _master(url: str, config: str | None, node: int | None) -> Any:
    from hil.servo.config import load_drive_config
    from hil.servo.rig import open_drive

    overrides = {"master": {"node_id": node}} if node else {}
    return open_drive(url, load_drive_config(config, overrides=overrides))


def _bus_lock(url: str) -> contextlib.AbstractContextManager[Any]:
    """The bus locked for this command, as a run locks it (an emulated drive is our own)."""
    from hil.core.device_lock import lock_device

    return contextlib.nullcontext() if url == "emulated" else lock_device(url, "drive bus")


def scan_command(args: argparse.Namespace) -> int:
    from drivers.canopen.scan import scan

    with _bus_lock(args.url):
        master = _master(args.url, args.config, None)
        try:
            reports = scan(master.link, args.node, master.config.mode)
        finally:
            master.disconnect()
    if args.json:
        print(json.dumps({"url": args.url, "mode": master.config.mode,
                          "nodes": [r.as_dict() for r in reports]}, indent=2))
    else:
        print(format_scan(args.url, master.config.mode, reports))
    return 0 if reports else 1


def format_scan(url: str, mode: str, reports: list[Any]) -> str:
    if not reports:
        return f"{url}: no node answered"
    lines = [f"{url}: {len(reports)} node(s)"]
    for r in reports:
        identity = ", ".join(f"{k} 0x{v:X}" for k, v in r.identity.items()) or "-"
        device = f"0x{r.device_type:08X}" if r.device_type is not None else "-"
        lines += [
            f"node {r.node_id}: {r.device_name or 'unnamed'}, NMT {r.nmt_state}",
            f"  device type {device}, identity {identity}",
            f"  error register {'-' if r.error_register is None else hex(r.error_register)}, "
            f"history {', '.join(r.error_history) or 'empty'}",
            f"  supported modes "
            f"{'-' if r.supported_modes is None else hex(r.supported_modes)}, heartbeat "
            f"{'-' if r.heartbeat_ms is None else str(r.heartbeat_ms) + ' ms'}",
        ]
        for pdo in r.pdos:
            lines.append(f"  {pdo.name} 0x{pdo.cob_id:03X} {'valid' if pdo.valid else 'off'}"
                         f", type {pdo.transmission}: {', '.join(pdo.mapped) or 'nothing mapped'}")
        lines.append(f"  hil can drive it in {mode.upper()}: " + (
            "yes" if r.drivable else "no: " + "; ".join(r.problems)))
    return "\n".join(lines)


def reset_command(args: argparse.Namespace) -> int:
    from drivers.cia402 import state_of

    with _bus_lock(args.url):
        master = _master(args.url, args.config, args.node)
        try:
            before = state_of(master.states.reach())
            master.clear_fault()
            after = state_of(master.states.statusword())
        finally:
            master.disconnect()
    if before == after:
        print(f"drive node {args.node}: {after}, nothing to reset")
    else:
        print(f"drive node {args.node}: {before} -> {after}")
    return 0


def plan_command(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from drivers.can_bus_time import plan_bus
    from drivers.canopen.master import axis_traffic
    from hil.servo.config import load_drive_config

    master = load_drive_config(args.config).master
    if args.rate_hz:
        master = replace(master, cycle_period_s=1.0 / args.rate_hz)
    if args.bitrate:
        master = replace(master, bitrate=args.bitrate)
    plan = plan_bus(master.bitrate, master.cycle_period_s,
                    [axis_traffic(master, f"axis {i}") for i in range(1, args.axes + 1)],
                    master_heartbeat_s=master.heartbeat_period_ms / 1e3)
    if args.json:
        print(json.dumps({"mode": master.mode, **plan.summary()}, indent=2))
    else:
        print(format_plan(master.mode, plan))
    return 0 if plan.fits else 1


def format_plan(mode: str, plan: Any) -> str:
    b = plan.budget
    axis = plan.axes[0]
    lines = [
        f"{len(plan.axes)} {'axis' if len(plan.axes) == 1 else 'axes'} in {mode.upper()} on "
        f"one bus at {b.bitrate} bit/s, "
        f"cycle {b.period_us:.0f} us ({1e6 / b.period_us:.0f} Hz): one SYNC, per axis an "
        f"RPDO of {axis.rpdo_bytes} bytes and TPDOs of "
        f"{' + '.join(str(n) for n in axis.tpdo_bytes)} bytes, heartbeats",
        f"  bus time per cycle {b.nominal_us:.0f} us without bit stuffing, {b.worst_us:.0f} us "
        f"with the worst case: {100 * b.load_worst:.0f} % of the period",
        f"  at this period at most {plan.max_axes} such "
        f"{'axis fits' if plan.max_axes == 1 else 'axes fit'}; these fit from "
        f"{plan.min_period_us:.0f} us ({1e6 / plan.min_period_us:.0f} Hz) on",
        "  fits" if plan.fits else f"  does not fit: {plan.problem()}",
    ]
    return "\n".join(lines)
