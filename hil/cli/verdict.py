"""The flags every run command shares for plug-in controllers and verdicts: ``--param``,
``--limit``, ``--junit``, ``--controller-budget``; and the exit status of a verdict."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from hil.cli.argtypes import output_file, positive_float
from hil.core.errors import UsageError
from hil.core.params import parse_param
from hil.core.verdict import LimitResult, junit_xml, parse_limit

SPEC_HELP = ("the controller: a built-in name ({builtins}), FILE.py:Class, "
             "package.module:Class, or a name an installed package registers in the "
             "'hil.controllers' entry points")


def _argument(parse: Callable[[str], Any], flag: str) -> Callable[[str], Any]:
    """``parse`` as an argparse type: its UsageError becomes argparse's one-line error."""
    def convert(text: str) -> Any:
        try:
            return parse(text)
        except UsageError as exc:
            raise argparse.ArgumentTypeError(
                str(exc).removeprefix(f"{flag} {text!r}: ")) from None

    return convert


_limit = _argument(parse_limit, "--limit")
_param = _argument(parse_param, "--param")


def add_controller_arguments(parser: argparse.ArgumentParser, builtins: str,
                             signals: str) -> None:
    """``--controller SPEC`` and the flags that go with a plug-in controller and a verdict."""
    parser.add_argument("--controller", required=True, metavar="SPEC",
                        help=SPEC_HELP.format(builtins=builtins))
    parser.add_argument("--param", action="append", type=_param, default=[],
                        metavar="KEY=VALUE", help="a parameter of the controller (repeat; "
                        "numbers are parsed as numbers), laid over the config's [controller]")
    parser.add_argument("--controller-budget", type=positive_float, metavar="S",
                        help="longest time one call of the controller may take before the run "
                        "stops to the safe state")
    parser.add_argument("--limit", action="append", type=_limit, default=[],
                        metavar="'KPI<=V'", help="a limit the run must hold (repeat; also a "
                        "[limits] table): KPI<=V or KPI>=V on a KPI of --json (nested keys "
                        f"joined by '.'), or on a per-tick signal ({signals}), which stops the "
                        "run to the safe state at once when crossed. Exit status 1 when one "
                        "is violated")


def add_junit_argument(parser: argparse.ArgumentParser) -> None:
    """``--junit F.xml`` of a single run."""
    parser.add_argument("--junit", metavar="F.xml", type=output_file,
                        help="write a JUnit XML report: one test case per limit")


def params_of(args: argparse.Namespace) -> dict[str, Any]:
    return dict(args.param)


#: exit status of a run that completed (no limit violated) but whose hardware misbehaved
EXIT_DISTURBED = 3


def disturbance_line(kpis: Mapping[str, Any]) -> str:
    """One line naming what disturbed the run (``faults`` KPIs that are not zero)."""
    faults = kpis.get("faults", {})
    seen = ", ".join(f"{name} {value}" for name, value in faults.items() if value)
    return (f"hil: run disturbed ({kpis.get('stop_reason', 'completed')}): {seen or 'faults'}; "
            "the KPIs exclude what the hardware did not report")


def finish(kpis: Mapping[str, Any], args: argparse.Namespace, suite: str,
           duration_s: float) -> int:
    """Write the JUnit report, name every violated limit and a disturbance on stderr; the
    exit status: 1 a limit violated, else 3 the run was disturbed (``disturbed``), else 0."""
    results = [LimitResult(parse_limit(row["limit"]), row["measured"], row["passed"])
               for row in kpis.get("limits", [])]
    if args.junit:
        path = Path(args.junit)
        try:
            path.write_bytes(junit_xml(results, suite, duration_s=duration_s,
                                       properties={"mcap": str(kpis.get("mcap", ""))}))
        except OSError as exc:
            raise UsageError(f"--junit {args.junit}: cannot write it: {exc.strerror}") from None
    failed = [r for r in results if not r.passed]
    for result in failed:
        print(f"hil: limit violated: {result.describe()}", file=sys.stderr)
    if kpis.get("disturbed"):
        print(disturbance_line(kpis), file=sys.stderr)
    if failed:
        return 1
    return EXIT_DISTURBED if kpis.get("disturbed") else 0
