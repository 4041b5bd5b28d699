"""``hil emulate bench|drive``: standalone emulator processes."""

from __future__ import annotations

import argparse

from hil.commands import not_yet_available
from hil.commands.argtypes import host_port, positive_int


def register(subparsers: argparse._SubParsersAction) -> None:
    emulate = subparsers.add_parser("emulate", help="run an emulator as a standalone process")
    emu_sub = emulate.add_subparsers(dest="emulate_command", metavar="DEVICE", required=True)
    eb = emu_sub.add_parser("bench", help="relay bench over Modbus TCP or RTU")
    where = eb.add_mutually_exclusive_group(required=True)
    where.add_argument("--tcp", type=host_port, metavar="HOST:PORT")
    where.add_argument("--serial", metavar="PORT")
    eb.set_defaults(handler=not_yet_available("hil emulate bench"))
    ed = emu_sub.add_parser("drive", help="CiA 402 servo drive over socketcand")
    ed.add_argument("--socketcand", type=host_port, metavar="HOST:PORT", required=True)
    ed.add_argument("--node", type=positive_int, default=1)
    ed.set_defaults(handler=not_yet_available("hil emulate drive"))
