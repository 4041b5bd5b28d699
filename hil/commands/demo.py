"""``hil demo``: EEC vs BC and MPC vs PID against the built-in emulators."""

from __future__ import annotations

import argparse

from hil.commands import not_yet_available


def register(subparsers: argparse._SubParsersAction) -> None:
    demo = subparsers.add_parser(
        "demo", help="EEC vs BC on the emulated bench, MPC vs PID on the emulated drive",
        description="The embedded default experiment against the built-in emulators (lockstep): "
        "bench over Modbus TCP on loopback, EEC vs BC for 8 machine cycles; drive over CAN, MPC "
        "vs PID on a 2 deg sine. Writes MCAP files and PNG reports, prints comparison tables.",
    )
    demo.add_argument("--out", default="out", metavar="DIR", help="output folder (default: out)")
    demo.set_defaults(handler=not_yet_available("hil demo"))
