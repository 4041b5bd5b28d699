"""``--place NAME`` of ``hil bench run`` and ``hil servo run``: the run on a labgrid place.
The place resolves to the flags a run already has (``--bench`` / ``--drive``, ``--node``,
``--eds``, ``--config``) and is held for the run (:func:`hil.lab.place.hold_place`); the
session's ``run`` metadata records it under ``lab``. Nothing here imports labgrid until a
run names a place (:mod:`hil.lab`)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from hil.errors import UsageError

#: the resource class a run's kind needs, and its fields -> the run's flags (argparse dests)
KINDS = {
    "bench": ("HilBench", {"url": "bench", "config": "config"}),
    "servo": ("HilDrive", {"url": "drive", "node": "node", "eds": "eds", "config": "config"}),
}


FIELDS = {"bench": "and its --config", "drive": "and its --node, --eds, --config"}


def add_place_arguments(parser: argparse.ArgumentParser, device: str) -> None:
    """``--place``, ``--coordinator`` and ``--wait`` (``device``: ``bench`` or ``drive``)."""
    parser.add_argument("--place", metavar="NAME",
                        help=f"run on this labgrid place (pip install 'hil[lab]'): its Hil"
                        f"{device.capitalize()} resource gives the {device} URL "
                        f"({FIELDS[device]}); the place is acquired for the run unless you "
                        "hold it already, and released after the safe stop")
    parser.add_argument("--coordinator", metavar="HOST:PORT",
                        help="the labgrid coordinator of --place (default: LG_COORDINATOR, "
                        "else 127.0.0.1:20408)")
    parser.add_argument("--wait", type=_seconds, metavar="S",
                        help="a --place held by someone else: wait up to S seconds for it "
                        "(a labgrid reservation; default: refuse at once)")


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text}")
    return value


def run_on_place(args: argparse.Namespace, kind: str, command: Callable[[], int]) -> int:
    """``command()`` (the run) with ``args`` pointed at the place's resource, the place held
    around it; without ``--place``, ``command()`` alone."""
    if args.place is None:
        for flag in ("coordinator", "wait"):
            if getattr(args, flag) is not None:
                raise UsageError(f"--{flag} goes with --place NAME")
        return command()
    try:
        from hil.lab.place import hold_place
    except ImportError as exc:
        raise UsageError(f"--place needs labgrid ({exc}): pip install 'hil[lab]'") from None

    cls, flags = KINDS[kind]
    if getattr(args, flags["url"]) is not None:
        raise UsageError(f"--place {args.place} and --{flags['url']} both say where the "
                         f"{flags['url']} is: give one")
    with hold_place(args.place, args.coordinator, args.wait or 0.0) as held:
        resource = held.one(cls)
        for name, dest in flags.items():
            value = resource.args.get(name)
            if value in (None, "", 0):
                continue
            if getattr(args, dest, None) is not None:
                raise UsageError(f"--{dest} and place {held.name}'s {cls} ({name} = {value!r}) "
                                 "both set it: give one")
            setattr(args, dest, value)
        args.lab = held.record()
        return command()
