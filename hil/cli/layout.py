"""``hil layout bench|servo [--out F]``: the shipped Foxglove layouts of the live view."""

from __future__ import annotations

import argparse
import shutil
from importlib import resources

from hil.cli.argtypes import output_file

LAYOUTS = {
    "bench": ("bench.json", "total VA against the limit, relays, levels q_j, the EEC's plan, "
                            "the run's parameters"),
    "servo": ("servo.json", "reference and position, error, current and its limits, the MPC "
                            "prediction, loop timing, the run's parameters"),
}


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "layout", help="the Foxglove layout of a live or recorded session",
        description="Print the path of a shipped Foxglove layout (Foxglove: layout menu > "
        "Import from file...), or write a copy with --out. "
        + "; ".join(f"{name}: {what}" for name, (_, what) in LAYOUTS.items()) + ".")
    parser.add_argument("kind", choices=sorted(LAYOUTS), help="which session the layout shows")
    parser.add_argument("--out", metavar="F.json", type=output_file, help="write the layout here")
    parser.set_defaults(handler=layout_command)


def layout_path(kind: str) -> str:
    """The installed layout file of ``kind`` (``bench`` or ``servo``)."""
    return str(resources.files("hil.layouts").joinpath(LAYOUTS[kind][0]))


def layout_command(args: argparse.Namespace) -> int:
    path = layout_path(args.kind)
    if args.out:
        try:
            shutil.copyfile(path, args.out)
        except OSError as exc:
            from hil.errors import UsageError
            raise UsageError(f"--out {args.out}: {exc.strerror or exc}") from None
        print(args.out)
    else:
        print(path)
    return 0
