"""``hil identify``: N4SID models from recorded sessions."""

from __future__ import annotations

import argparse

from hil.commands import not_yet_available
from hil.commands.argtypes import positive_int


def register(subparsers: argparse._SubParsersAction) -> None:
    identify = subparsers.add_parser("identify", help="N4SID model from a recorded session")
    identify.add_argument("file")
    identify.add_argument("--order", type=positive_int)
    identify.add_argument("--json", action="store_true")
    identify.set_defaults(handler=not_yet_available("hil identify"))
