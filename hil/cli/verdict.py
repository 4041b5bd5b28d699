"""The flags every run command shares for plug-in controllers and verdicts: ``--param``,
``--limit``, ``--junit``, ``--controller-budget``; and the shared end of a run command: its
report (``--json``, ``--junit``) for every outcome and its exit status."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from hil.cli.argtypes import output_file, positive_float
from hil.cli.output import json_text
from hil.core.params import parse_param
from hil.core.verdict import (
    LimitResult,
    RunCase,
    junit_xml,
    kpi_properties,
    parse_limit,
    run_status,
)
from hil.errors import HilError, RunInterruptedError, UsageError

if TYPE_CHECKING:
    from hil.core.run import RunResult

Options = TypeVar("Options")

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
    parser.add_argument("--controller", metavar="SPEC",
                        help=SPEC_HELP.format(builtins=builtins))
    add_param_argument(parser, "laid over the config's [controller]")
    parser.add_argument("--params", metavar="F.toml",
                        help="the controller's parameters from a file, NAME = VALUE each (a "
                        "sweep's best.toml), laid over the config's [controller]; --param "
                        "flags win")
    parser.add_argument("--controller-budget", type=positive_float, metavar="S",
                        help="longest time one call of the controller may take before the run "
                        "stops to the safe state")
    parser.add_argument("--limit", action="append", type=_limit, default=[],
                        metavar="'KPI<=V'", help="a limit the run must hold (repeat; also a "
                        "[limits] table): KPI<=V or KPI>=V on a KPI of --json (nested keys "
                        f"joined by '.'), or on a per-tick signal ({signals}), which stops the "
                        "run to the safe state at once when crossed. Exit status 1 when one "
                        "is violated")


def add_param_argument(parser: argparse.ArgumentParser, laid_over: str) -> None:
    """``--param KEY=VALUE`` (repeat), its values ``laid_over`` what the help names."""
    parser.add_argument("--param", action="append", type=_param, default=[],
                        metavar="KEY=VALUE", help="a parameter of the controller (repeat; "
                        f"numbers are parsed as numbers), {laid_over}")


def add_junit_argument(parser: argparse.ArgumentParser) -> None:
    """``--junit F.xml`` of a single run."""
    parser.add_argument("--junit", metavar="F.xml", type=output_file,
                        help="write a JUnit XML report, whatever the run's outcome: one test "
                        "case per limit (a failure where violated) and the test case 'run' (an "
                        "error when it was stopped, failed or interrupted); the KPIs and the "
                        "session as properties")


def params_of(args: argparse.Namespace) -> dict[str, Any]:
    return dict(args.param)


#: exit status of a run that completed (no limit violated) but whose hardware misbehaved
EXIT_DISTURBED = 3
#: exit status of a run, however it ended, whose outputs are not known to be safe (status
#: ``unsafe``: a safe stop that did not complete, relays not confirmed at their safe levels)
EXIT_UNSAFE = 4


def disturbance_line(kpis: Mapping[str, Any]) -> str:
    """One line naming what disturbed the run (``faults`` KPIs that are not zero)."""
    faults = kpis.get("faults", {})
    seen = ", ".join(f"{name} {value}" for name, value in faults.items() if value)
    return (f"hil: run disturbed ({kpis.get('stop_reason', 'completed')}): {seen or 'faults'}; "
            "the KPIs exclude what the hardware did not report")


def _unsafe_case(kpis: Mapping[str, Any], after: BaseException | None = None) -> RunCase:
    """The JUnit ``run`` case of an unsafe run: an ``UnsafeStop`` error naming each device,
    and the error that ended the run, if one did."""
    ended = f" (the run ended: {type(after).__name__}: {after})" if after is not None else ""
    return RunCase("; ".join(kpis.get("unsafe", ())) + ended, "UnsafeStop")


def finish(args: argparse.Namespace, command: str, options: Callable[[], Options],
           run: Callable[[Options], RunResult],
           summary: Callable[[Options, dict[str, Any]], str]) -> int:
    """Run ``run(options())`` and report it, whatever its outcome: the KPIs on stdout
    (``--json``, else ``summary``), the JUnit report (``--junit``), every violated limit and a
    disturbance on stderr; the exit status: 1 a limit violated, else 3 the run was disturbed,
    else 0. A run that ended in an error (a safety stop, a fault, a lost link, Ctrl-C...) still
    prints ``--json`` (the KPIs so far, ``status``, ``error``) and writes ``--junit``; then the
    error is raised again for its one line and exit status. A run whose outputs are not known
    to be safe (status ``unsafe``; a ``hil: unsafe:`` line per device was printed when the
    device said so), however it ended, exits 4."""
    started = time.perf_counter()
    try:
        made = options()
        kpis = run(made).kpis
    except (HilError, KeyboardInterrupt) as exc:
        _report_error(exc, args, command, time.perf_counter() - started)
        result = exc.result if isinstance(exc, HilError) else None
        if result is None or not result.kpis.get("unsafe"):
            raise
        prefix = "hil: " if isinstance(exc, RunInterruptedError) else "hil: error: "
        print(f"{prefix}{exc}", file=sys.stderr)
        return EXIT_UNSAFE
    print(json_text(kpis) if args.json else summary(made, kpis))
    results = limit_results(kpis)
    disturbed = bool(kpis.get("disturbed"))
    write_junit(args, kpis, f"{command} {kpis['controller']}", time.perf_counter() - started,
                results, _unsafe_case(kpis) if kpis.get("unsafe") else
                RunCase(disturbance_line(kpis).removeprefix("hil: "), "RunDisturbed")
                if disturbed else RunCase(_ending(kpis)))
    failed = [r for r in results if not r.passed]
    for result in failed:
        print(f"hil: limit violated: {result.describe()}", file=sys.stderr)
    if disturbed:
        print(disturbance_line(kpis), file=sys.stderr)
    if kpis.get("unsafe"):
        return EXIT_UNSAFE
    if failed:
        return 1
    return EXIT_DISTURBED if disturbed else 0


def _ending(kpis: Mapping[str, Any]) -> str:
    """How a run without error ended: ``completed``, ``violated: stopped by limit ...``."""
    reason = kpis.get("stop_reason")
    if reason in (None, "completed"):
        return str(kpis["status"])
    return f"{kpis['status']}: stopped by {reason}"


def _report_error(exc: HilError | KeyboardInterrupt, args: argparse.Namespace, command: str,
                  duration_s: float) -> None:
    """``--json`` and ``--junit`` of a run an error ended: its KPIs so far, or (the error came
    before the run) the error alone. A report that cannot be written is one more line."""
    result = exc.result if isinstance(exc, HilError) else None
    if result is not None:
        kpis = result.kpis
    else:
        kpis = {"controller": getattr(args, "controller", None), "mcap": None,
                "stop_reason": None, "status": run_status({}, exc),
                "error": str(exc) or "interrupted"}
    if args.json:
        print(json_text(kpis))
    case = _unsafe_case(kpis, exc) if kpis.get("unsafe") else \
        RunCase(str(exc) or "interrupted", type(exc).__name__)
    try:
        write_junit(args, kpis, f"{command} {kpis['controller']}", duration_s,
                    limit_results(kpis), case)
    except UsageError as failure:
        print(f"hil: error: {failure}", file=sys.stderr)


def limit_results(kpis: Mapping[str, Any]) -> list[LimitResult]:
    """The ``limits`` rows of a KPI document as results."""
    return [LimitResult(parse_limit(row["limit"]), row["measured"], row["passed"])
            for row in kpis.get("limits", [])]


def write_junit(args: argparse.Namespace, kpis: Mapping[str, Any], suite: str,
                duration_s: float, results: list[LimitResult], run: RunCase) -> None:
    """``--junit``: the limits and the run as test cases, the KPIs as properties."""
    if not args.junit:
        return
    path = Path(args.junit)
    try:
        path.write_bytes(junit_xml(results, suite, duration_s=duration_s,
                                   properties=kpi_properties(kpis), run=run))
    except OSError as exc:
        raise UsageError(f"--junit {args.junit}: cannot write it: {exc.strerror}") from None
