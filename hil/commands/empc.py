"""``hil empc build``: explicit MPC regions, search tree, C export."""

from __future__ import annotations

import argparse

from hil.commands import not_yet_available
from hil.commands.argtypes import positive_int


def register(subparsers: argparse._SubParsersAction) -> None:
    empc = subparsers.add_parser("empc", help="explicit MPC: build regions, tree, C code")
    empc_sub = empc.add_subparsers(dest="empc_command", metavar="COMMAND", required=True)
    build = empc_sub.add_parser("build", help="solve the mpQP and build the search tree")
    build.add_argument("--ht", type=positive_int, default=3)
    build.add_argument("--hp", type=positive_int, default=50)
    build.add_argument("--ert", choices=["foh", "zoh"], default="foh")
    build.add_argument("--json", action="store_true")
    build.add_argument("--export-c", metavar="F.c")
    build.set_defaults(handler=not_yet_available("hil empc build"))
