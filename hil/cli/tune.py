"""``hil tune HOST:PORT NAME=VALUE... [--list] [--json]``: set a running session's parameters."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hil.errors import UsageError

EXIT_REFUSED = 1


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "tune", help="set a running session's parameters (controller gains, safety limits)",
        description="Set parameters of a session that runs with --live, as Foxglove's "
        "Parameters panel does: each NAME=VALUE is checked by the run (range, type, a safety "
        "limit only stricter), applied at a tick boundary and recorded. Prints the value in "
        "force afterwards, or the reason of a refusal. Exit status 0: all accepted, "
        "1: one refused, 2: the live view cannot be reached.")
    parser.add_argument("address", metavar="HOST:PORT",
                        help="the session's live view (its --live; HOST 127.0.0.1 if left out)")
    parser.add_argument("assignments", metavar="NAME=VALUE", nargs="*",
                        help="e.g. controller.kp=5 (VALUE: a number, true/false or text)")
    parser.add_argument("--list", action="store_true",
                        help="print every parameter and its value (after the sets)")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    parser.set_defaults(handler=tune_command)


def parse_assignment(text: str) -> tuple[str, Any]:
    """``NAME=VALUE``: VALUE as a JSON number or true/false, else as text."""
    name, sep, value_text = text.partition("=")
    if not sep or not name.strip() or not value_text.strip():
        raise UsageError(f"tune: expected NAME=VALUE (e.g. controller.kp=5), got {text!r}")
    value: Any = value_text.strip()
    try:
        parsed = json.loads(value)
    except ValueError:
        parsed = value
    if isinstance(parsed, (bool, int, float)):
        value = parsed
    return name.strip(), value


def tune_command(args: argparse.Namespace) -> int:
    from hil.core.recording.live import parse_address
    from hil.core.recording.tune_client import TuneClient

    assignments = [parse_assignment(text) for text in args.assignments]
    if not assignments and not args.list:
        raise UsageError("tune: give NAME=VALUE to set, or --list")
    try:
        host, port = parse_address(args.address)
    except UsageError:
        raise UsageError(f"tune: expected HOST:PORT with PORT 0-65535, got "
                         f"{args.address!r}") from None
    client = TuneClient(host, port)
    try:
        answers = [client.set(name, value) for name, value in assignments]
        listing = client.parameters() if args.list else None
    finally:
        client.close()
    if args.json:
        document: dict[str, Any] = {"results": [
            {"name": a.name, "requested": a.requested, "accepted": a.accepted,
             "value": a.value, "reason": a.reason} for a in answers]}
        if listing is not None:
            document["parameters"] = listing
        print(json.dumps(document))
    else:
        for a in answers:
            print(f"{a.name} = {a.value!r}" if a.accepted else
                  f"{a.name} = {a.requested!r} refused: {a.reason}",
                  file=sys.stdout if a.accepted else sys.stderr)
        for name, value in (listing or {}).items():
            print(f"{name} = {value!r}")
    return EXIT_REFUSED if any(not a.accepted for a in answers) else 0
