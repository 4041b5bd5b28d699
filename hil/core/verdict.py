"""Limits on a run's KPIs, the verdict they give and the run's ``status``, with a JUnit XML
report for any CI.

A limit is ``KPI<=VALUE`` or ``KPI>=VALUE`` (``<`` and ``>`` too). ``KPI`` is a key of the run's
KPI dictionary, a nested one joined by dots (``solve_ms.p99``). In a config file::

    [limits]
    J2_VA = { max = 560.0 }
    "step_us.p99" = { max = 100.0 }
    rms_error_deg = { max = 0.05, min = 0.0 }
"""

from __future__ import annotations

import json
import math
import operator
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from hil.core.config import Table
from hil.errors import ConfigError, RunInterruptedError, SafetyStopError, UsageError

_OPERATORS: dict[str, Callable[[float, float], bool]] = {
    "<=": operator.le, ">=": operator.ge, "<": operator.lt, ">": operator.gt,
}
_LIMIT = re.compile(r"^\s*([A-Za-z_][\w.\-]*)\s*(<=|>=|<|>)\s*(\S+)\s*$")


@dataclass(frozen=True)
class Limit:
    """``kpi op value``, e.g. ``J2_VA <= 560``."""

    kpi: str
    op: str
    value: float

    def __str__(self) -> str:
        return f"{self.kpi}{self.op}{self.value:g}"


@dataclass(frozen=True)
class LimitResult:
    """One limit checked on a run: ``measured`` is None when the run has no such KPI."""

    limit: Limit
    measured: float | None
    passed: bool

    def describe(self) -> str:
        """``J2_VA<=560: measured 604.1 (violated)``."""
        if self.measured is None:
            return f"{self.limit}: no KPI {self.limit.kpi!r} in this run (violated)"
        verdict = "holds" if self.passed else "violated"
        return f"{self.limit}: measured {self.measured:g} ({verdict})"


def parse_limit(text: str) -> Limit:
    """``'J2_VA<=560'`` -> Limit; a UsageError names the text and the expected form."""
    match = _LIMIT.match(text)
    if not match:
        raise UsageError(f"--limit {text!r}: expected KPI<=VALUE or KPI>=VALUE, e.g. "
                         "'J2_VA<=560'")
    kpi, op, value_text = match.groups()
    try:
        value = float(value_text)
    except ValueError:
        raise UsageError(f"--limit {text!r}: {value_text!r} is not a number") from None
    if not math.isfinite(value):
        raise UsageError(f"--limit {text!r}: the value must be finite")
    return Limit(kpi, op, value)


def limits_from_table(table: Table) -> list[Limit]:
    """The ``[limits]`` table: ``KPI = { max = V, min = V }`` (either or both)."""
    limits = []
    for kpi in table.names():
        bounds = table.table(kpi, required=True)
        low, high = bounds.number("min", None), bounds.number("max", None)
        bounds.done()
        if low is None and high is None:
            raise ConfigError(f"{table.source}: key '{table.key(kpi)}' needs min, max or both")
        if low is not None:
            limits.append(Limit(kpi, ">=", low))
        if high is not None:
            limits.append(Limit(kpi, "<=", high))
    return limits


def kpi_value(kpis: Mapping[str, Any], dotted: str) -> float | None:
    """``kpis['solve_ms']['p99']`` for ``'solve_ms.p99'``; None when absent or not a number."""
    node: Any = kpis
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    if isinstance(node, bool) or not isinstance(node, int | float):
        return None
    return float(node)


def check_limits(limits: Sequence[Limit], kpis: Mapping[str, Any]) -> list[LimitResult]:
    """Every limit against the run's KPIs. A missing KPI or a NaN violates its limit."""
    results = []
    for limit in limits:
        measured = kpi_value(kpis, limit.kpi)
        passed = measured is not None and not math.isnan(measured) and \
            _OPERATORS[limit.op](measured, limit.value)
        results.append(LimitResult(limit, measured, passed))
    return results


#: what became of a run (the ``status`` KPI), with the exit status of ``hil bench|servo run``:
#: completed 0, violated 1 (a limit), disturbed 3 (the hardware misbehaved), stopped 2 (a
#: safety limit), failed 2 (a fault, a lost link, a controller error...), unsafe 4 (however
#: it ended, its outputs are not known to be safe: see UNSAFE_EVENTS), interrupted 130/143
STATUSES = ("completed", "violated", "disturbed", "stopped", "failed", "unsafe", "interrupted")
#: the events that make a run ``unsafe``: the drive's safe stop did not complete (the axis may
#: still move), the bench's relays are not confirmed at their safe levels; each event's message
#: is the line the run reports (the KPIs' ``unsafe``)
UNSAFE_EVENTS = ("drive.safe_stop_failed", "bench.safe_state_unconfirmed")


def run_status(kpis: Mapping[str, Any], error: BaseException | None) -> str:
    """The run's ``status`` (one of :data:`STATUSES`): unsafe when its KPIs carry ``unsafe``
    lines, whatever else happened; else stopped by a signal, by a safety limit or by another
    error; else a limit violated, the hardware misbehaved, or neither."""
    if kpis.get("unsafe"):
        return "unsafe"
    if isinstance(error, RunInterruptedError | KeyboardInterrupt):
        return "interrupted"
    if isinstance(error, SafetyStopError):
        return "stopped"
    if error is not None:  # the hardware gone (exit 3) is a disturbed run, not a failed one
        return "disturbed" if getattr(error, "exit_status", 2) == 3 else "failed"
    if kpis.get("passed") is False:
        return "violated"
    return "disturbed" if kpis.get("disturbed") else "completed"


def kpi_properties(kpis: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """The KPI document as flat ``name -> text`` properties (nested keys joined by '.', the
    ``limits`` rows left out: they are test cases); text as-is, anything else as JSON."""
    flat: dict[str, str] = {}
    for key, value in kpis.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(kpi_properties(value, f"{name}."))
        elif not (key == "limits" and not prefix):
            flat[name] = value if isinstance(value, str) else json.dumps(value, default=str)
    return flat


@dataclass(frozen=True)
class RunCase:
    """The run itself as a JUnit test case: an ``<error>`` of type ``error_type`` (the error's
    class, ``RunDisturbed``...) with ``message``, or passed (``message`` as its output)."""

    message: str
    error_type: str | None = None


def junit_xml(results: Sequence[LimitResult], suite: str, *, duration_s: float = 0.0,
              properties: Mapping[str, str] | None = None, run: RunCase | None = None) -> bytes:
    """A JUnit XML report (``testsuites/testsuite/testcase``, as GitLab and Jenkins read it):
    one test case per limit, a ``<failure>`` where it is violated; then, with ``run``, the
    test case ``run``, an ``<error>`` when the run did not end well. ``properties`` (the KPIs,
    the session) go on the suite."""
    import xml.etree.ElementTree as ET  # here: only a run asked for JUnit needs it

    failures = sum(not r.passed for r in results)
    errors = int(run is not None and run.error_type is not None)
    tests = len(results) + int(run is not None)
    root = ET.Element("testsuites", name="hil", tests=str(tests), failures=str(failures),
                      errors=str(errors), time=f"{duration_s:.3f}")
    node = ET.SubElement(root, "testsuite", name=suite, tests=str(tests),
                         failures=str(failures), errors=str(errors), skipped="0",
                         time=f"{duration_s:.3f}")
    if properties:
        props = ET.SubElement(node, "properties")
        for key, value in properties.items():
            ET.SubElement(props, "property", name=key, value=str(value))
    for result in results:
        # each limit is judged on the whole run: the run's time is each case's time
        case = ET.SubElement(node, "testcase", classname=suite, name=str(result.limit),
                             time=f"{duration_s:.3f}")
        props = ET.SubElement(case, "properties")
        ET.SubElement(props, "property", name="measured", value=str(result.measured))
        ET.SubElement(props, "property", name="unit", value=unit_of(result.limit.kpi))
        if not result.passed:
            failure = ET.SubElement(case, "failure", message=result.describe(),
                                    type="LimitViolated")
            failure.text = result.describe()
        else:
            ET.SubElement(case, "system-out").text = result.describe()
    if run is not None:
        case = ET.SubElement(node, "testcase", classname=suite, name="run",
                             time=f"{duration_s:.3f}")
        if run.error_type is not None:
            error = ET.SubElement(case, "error", message=run.message, type=run.error_type)
            error.text = run.message
        else:
            ET.SubElement(case, "system-out").text = run.message
    ET.indent(root)
    return ET.tostring(root, encoding="utf-8", xml_declaration=True)


#: units by the ending of a KPI or signal name (hil names carry their unit)
UNITS = (("_VAs", "VA·s"), ("_VA", "VA"), ("_mA", "mA"), ("_deg_s", "deg/s"), ("_deg", "deg"),
         ("_pct", "%"), ("_ms", "ms"), ("_us", "us"), ("_s", "s"))


def unit_of(name: str) -> str:
    """The unit of a KPI or signal from its name (``rms_error_deg`` -> deg; '' if none)."""
    last = name.split(".")[0] if "." in name and name.split(".")[-1] in (
        "median", "p99", "max") else name.split(".")[-1]
    return next((unit for ending, unit in UNITS if last.endswith(ending)), "")


RUN_TABLES = ("controller", "limits")


@dataclass(frozen=True)
class RunTables:
    """The tables of a config file that belong to a run rather than to a device:
    ``[controller]`` (the params of the controller) and ``[limits]``."""

    params: Mapping[str, Any]
    limits: tuple[Limit, ...]


def read_run_tables(top: Table) -> RunTables:
    """``[controller]`` (any keys: the controller checks them) and ``[limits]`` of ``top``."""
    params = top.table("controller")
    values = {name: params.value(name) for name in params.names()}
    return RunTables(values, tuple(limits_from_table(top.table("limits"))))


class SignalWatch:
    """Limits on per-tick signals (a run's ``power_va``, ``abs_error_deg``...): every sample is
    checked, the worst value of each signal is kept, and the first violation is reported so the
    run can stop at once, its outputs in their safe state."""

    def __init__(self, limits: Sequence[Limit]) -> None:
        self.limits = tuple(limits)
        self.worst: dict[Limit, float] = {}
        self.violation: LimitResult | None = None

    def check(self, values: Mapping[str, float]) -> LimitResult | None:
        """The first violation among ``values`` (signal -> value), once; None otherwise."""
        found = None
        for limit in self.limits:
            value = values.get(limit.kpi)
            if value is None:
                continue
            worst = self.worst.get(limit)
            upper = limit.op in ("<=", "<")
            if worst is None or (value > worst if upper else value < worst) or math.isnan(value):
                self.worst[limit] = value
            if found is None and self.violation is None and \
                    not _OPERATORS[limit.op](value, limit.value):
                found = self.violation = LimitResult(limit, value, False)
        return found

    def results(self) -> list[LimitResult]:
        """Each limit with the worst value seen (None: the signal never came)."""
        out = []
        for limit in self.limits:
            worst = self.worst.get(limit)
            passed = worst is not None and not math.isnan(worst) and \
                _OPERATORS[limit.op](worst, limit.value)
            out.append(LimitResult(limit, worst, passed))
        return out


def split_limits(limits: Sequence[Limit], signals: Sequence[str],
                 kpis: Sequence[str] | None = None) -> tuple[list[Limit], list[Limit]]:
    """(limits on the run's KPIs, limits on its per-tick ``signals``). With ``kpis`` (the
    application's KPI names; a nested one is named by its group, e.g. ``faults``), a limit on
    a name that is neither is a :class:`UsageError` listing both, before the run."""
    names = set(signals)
    if kpis is not None:
        known = set(kpis)
        for lim in limits:
            if lim.kpi not in names and lim.kpi.split(".")[0] not in known:
                raise UsageError(
                    f"limit '{lim}': no KPI or signal '{lim.kpi}'; KPIs: {', '.join(kpis)} "
                    f"(groups as GROUP.KEY, e.g. faults.emcy); per-tick signals: "
                    f"{', '.join(signals)}")
    return ([lim for lim in limits if lim.kpi not in names],
            [lim for lim in limits if lim.kpi in names])


def verdict(kpis: Mapping[str, Any], kpi_limits: Sequence[Limit], watch: SignalWatch | None
            ) -> dict[str, Any]:
    """``{"passed": bool, "limits": [...]}`` for a run's KPI document (empty without limits)."""
    results = [*(watch.results() if watch is not None else []),
               *check_limits(kpi_limits, kpis)]
    if not results:
        return {}
    return {"passed": all(r.passed for r in results),
            "limits": [{"limit": str(r.limit), "measured": r.measured, "passed": r.passed}
                       for r in results]}
