"""Two sessions held against each other: their KPIs and chosen signals, each against its
tolerance (:mod:`hil.compare.tolerances`), on one time base (:mod:`hil.compare.alignment`).

KPIs are those the run recorded (``hil report``'s ``kpis``), nested keys joined by dots; the
KPIs that measure the computer rather than the experiment (:data:`COMPUTER_KPIS`) are left
out unless a tolerance names them. Without a tolerance, a KPI or a signal is held exact when
both sessions are lockstep; in real time a KPI gets :data:`REALTIME_KPI_DEFAULT` and a signal
needs a tolerance of its own (or ``*``). ``worse:`` takes a KPI's side by its better direction
(:mod:`hil.compare.direction`); a signal has none. An axis' positions are compared relative to
each run's start when both runs started from where their axis stood
(:mod:`hil.compare.relative`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hil.compare.alignment import Aligned, Series, interpolated, tick_for_tick
from hil.compare.judge import judge_kpi, judge_signal
from hil.compare.relative import start_offsets
from hil.compare.tolerances import (
    BOTH,
    DEFAULT,
    EXACT,
    WORSE,
    Spelling,
    Tolerance,
    flag_spelling,
)
from hil.core.recording.reader import SessionData, read_session
from hil.core.report import kpis, session_kind
from hil.core.verdict import unit_of
from hil.errors import HilError, UsageError

#: KPIs left out unless a tolerance names them: they time the computer, not the machine
COMPUTER_KPIS = ("wall_s", "realtime_factor", "step_us", "solve_ms", "deadline_misses")
#: a KPI's tolerance in real time when none is given
REALTIME_KPI_DEFAULT = Tolerance("rel", 0.05)


class IncomparableError(HilError):
    """The two sessions cannot be compared (applications, rates, a signal missing): exit 2."""


@dataclass
class Row:
    """One KPI or signal: the two values (a signal's at ``worst_t_s``), the difference, the
    tolerance's text and the verdict."""

    kind: str
    name: str
    baseline: float | None
    candidate: float | None
    difference: float | None
    tolerance: str
    passed: bool
    worst_t_s: float | None = None
    #: a position taken relative to each run's start: (the baseline's, the candidate's) [deg]
    from_start_deg: tuple[float, float] | None = None

    @property
    def unit(self) -> str:
        return unit_of(self.name.rpartition(":")[2] or self.name)


@dataclass
class Comparison:
    """The comparison of a candidate session with a baseline (``to_json`` is its document)."""

    baseline: str
    candidate: str
    application: str
    alignment: str
    rows: list[Row] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    #: the log time [ns] each session's time counts from ("baseline", "candidate"): the first
    #: tick of the compared signals, else the session's first message
    origins_ns: dict[str, int] = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        return all(row.passed for row in self.rows)

    def failed(self) -> list[Row]:
        return [row for row in self.rows if not row.passed]

    def to_json(self) -> dict[str, Any]:
        return {"baseline": self.baseline, "candidate": self.candidate,
                "application": self.application, "alignment": self.alignment,
                "passed": self.passed,
                "rows": [{"kind": r.kind, "name": r.name, "baseline": _plain(r.baseline),
                          "candidate": _plain(r.candidate),
                          "difference": _plain(r.difference), "tolerance": r.tolerance,
                          "passed": r.passed, "worst_t_s": _plain(r.worst_t_s),
                          "unit": r.unit,
                          "from_start_deg": list(r.from_start_deg) if r.from_start_deg
                          else None} for r in self.rows],
                "notes": list(self.notes), "origins_ns": dict(self.origins_ns)}


def _plain(value: float | None) -> float | None:
    return value if value is None or math.isfinite(value) else None


def compare_sessions(baseline: str | os.PathLike[str], candidate: str | os.PathLike[str],
                     signals: Sequence[str] = (),
                     tolerances: Mapping[str, Tolerance] | None = None,
                     spelling: Spelling = flag_spelling) -> Comparison:
    """Compare the session ``candidate`` with ``baseline`` (files, split series or folders,
    damaged ones as ``hil report`` reads them). ``signals``: ``TOPIC:FIELD`` names; a signal a
    tolerance names is compared too. Raises :class:`IncomparableError` when the sessions
    cannot be compared, a UsageError (a tolerance written as ``spelling`` writes it) when a
    tolerance does not fit what it names."""
    return compare_data(read_session(baseline), read_session(candidate), signals, tolerances,
                        spelling)


def compare_data(base: SessionData, cand: SessionData, signals: Sequence[str] = (),
                 tolerances: Mapping[str, Tolerance] | None = None,
                 spelling: Spelling = flag_spelling) -> Comparison:
    """:func:`compare_sessions` of two sessions already read."""
    tolerances = dict(tolerances or {})
    application = _application(base, cand)
    lockstep = all(_session(d).get("clock") == "sim" for d in (base, cand))
    out = Comparison(base.path, cand.path, application,
                     "lockstep" if lockstep else "interpolated")
    if not lockstep:
        out.notes.append("real-time sessions: the candidate interpolated onto the baseline's "
                         "ticks")
    for role, data in (("baseline", base), ("candidate", cand)):
        if data.recovered:
            out.notes.append(f"{role} is a recovered file ({data.error}): compared over what "
                             "was read")
    only = sorted(set(base.messages) ^ set(cand.messages))
    if only:
        out.notes.append(f"topics in one session only: {', '.join(only)}")
    chosen = list(dict.fromkeys([*signals, *(n for n in tolerances if ":" in n)]))
    out.rows.extend(_kpi_rows(base, cand, tolerances, lockstep, out.notes, spelling))
    offsets = start_offsets(chosen, base, cand, out.notes)
    ours, out.origins_ns["baseline"] = _from_first_tick(
        [_from(series(base, name, "baseline"), offset, 0)
         for name, offset in zip(chosen, offsets, strict=True)], base)
    theirs, out.origins_ns["candidate"] = _from_first_tick(
        [_from(series(cand, name, "candidate"), offset, 1)
         for name, offset in zip(chosen, offsets, strict=True)], cand)
    for name, mine, other, offset in zip(chosen, ours, theirs, offsets, strict=True):
        row = _signal_row(name, mine, other, _tolerance(name, tolerances, lockstep, spelling),
                          lockstep, out.notes)
        row.from_start_deg = offset
        out.rows.append(row)
    if not out.rows:
        raise IncomparableError("nothing to compare: no KPI in both sessions (a recovered "
                                "file has none) and no --signal given")
    return out


def _session(data: SessionData) -> dict[str, str]:
    return data.metadata.get("session", {})


def _application(base: SessionData, cand: SessionData) -> str:
    kinds = session_kind(base), session_kind(cand)
    if kinds[0] != kinds[1]:
        raise IncomparableError(f"different applications: the baseline is a "
                                f"{kinds[0] or 'unknown'} session, the candidate a "
                                f"{kinds[1] or 'unknown'} session")
    periods = [_session(d).get("base_period_s") for d in (base, cand)]
    if periods[0] != periods[1]:
        raise IncomparableError(f"different rates: the baseline ticks every {periods[0]} s, "
                                f"the candidate every {periods[1]} s")
    return kinds[0]


def _tolerance(name: str, tolerances: Mapping[str, Tolerance], lockstep: bool,
               spelling: Spelling, kpi: bool = False) -> Tolerance:
    """The tolerance of a KPI or signal: its own, ``*``'s, else the default (``worse:``
    resolved: a KPI's by its direction; a signal has none: refused when named, else
    two-sided)."""
    if name in tolerances:
        named = tolerances[name]
        if kpi:
            return named.for_kpi(name, True, spelling)
        if named.side == WORSE:
            raise UsageError(f"{spelling(name, named.spec())}: a signal has no better "
                             "direction; bound it with max:V or min:V")
        return named
    if DEFAULT in tolerances and not (kpi and tolerances[DEFAULT].kind == "tube"):
        default = tolerances[DEFAULT]  # a tube for '*' is the signals' default only
        if kpi:
            return default.for_kpi(name, False, spelling)
        return replace(default, side=BOTH) if default.side == WORSE else default
    if lockstep:
        return EXACT
    if kpi:
        return REALTIME_KPI_DEFAULT
    raise UsageError(f"signal {name}: real-time sessions need a tolerance for it "
                     f"({spelling(name, 'abs:V')}, or {spelling(DEFAULT, '...')} for every "
                     "one)")


def flat_kpis(document: Mapping[str, Any], prefix: str = "") -> dict[str, float]:
    """The numeric KPIs of a KPI document, nested keys joined by dots (no booleans)."""
    out: dict[str, float] = {}
    for key, value in document.items():
        if isinstance(value, Mapping):
            out.update(flat_kpis(value, f"{prefix}{key}."))
        elif isinstance(value, int | float) and not isinstance(value, bool):
            out[f"{prefix}{key}"] = float(value)
    return out


def _kpi_rows(base: SessionData, cand: SessionData, tolerances: Mapping[str, Tolerance],
              lockstep: bool, notes: list[str], spelling: Spelling) -> list[Row]:
    ours, theirs = flat_kpis(kpis(base)), flat_kpis(kpis(cand))
    for name in tolerances:
        if name != DEFAULT and ":" not in name and not (name in ours and name in theirs):
            where = "either session" if name not in ours and name not in theirs else \
                ("the baseline" if name not in ours else "the candidate")
            raise IncomparableError(f"KPI {name}: not in {where}; KPIs of both: "
                                    f"{', '.join(sorted(set(ours) & set(theirs))) or 'none'}")
    if not ours or not theirs:
        notes.append(f"KPIs not compared: the {'baseline' if not ours else 'candidate'} "
                     "recorded none (a run that did not finish writes none)")
        return []
    only = sorted(set(ours) ^ set(theirs))
    if only:
        notes.append(f"KPIs in one session only, not compared: {', '.join(only)}")
    rows = []
    for name in (n for n in ours if n in theirs):
        if name.split(".")[0] in COMPUTER_KPIS and name not in tolerances:
            continue
        tolerance = _tolerance(name, tolerances, lockstep, spelling, kpi=True)
        if tolerance.kind == "tube":
            raise UsageError(f"{spelling(name, tolerance.spec())}: a tube is for signals "
                             "(TOPIC:FIELD); a KPI takes exact, abs:V, rel:P%, max:V, min:V "
                             "or worse:V")
        verdict = judge_kpi(tolerance, ours[name], theirs[name])
        rows.append(Row("kpi", name, ours[name], theirs[name], verdict.difference,
                        tolerance.text(name), verdict.passed))
    return rows


def series(data: SessionData, name: str, role: str) -> Series:
    """The signal ``TOPIC:FIELD`` of a session, its log times in ns."""
    topic, sep, key = name.rpartition(":")
    if not sep or not topic.startswith("/") or not key:
        raise UsageError(f"--signal {name!r}: expected TOPIC:FIELD, e.g. "
                         "/drive/feedback:position_deg")
    if topic not in data.messages:
        raise IncomparableError(f"signal {name}: the {role} has no topic {topic} (topics: "
                                f"{', '.join(sorted(data.messages))})")
    arrays = data.arrays(topic)
    if key not in arrays:
        fields = ", ".join(k for k in arrays if k != "log_time_ns")
        raise IncomparableError(f"signal {name}: the {role}'s {topic} has no field {key} "
                                f"(fields: {fields})")
    try:
        values = np.asarray(arrays[key], dtype=float)
    except (TypeError, ValueError):
        raise IncomparableError(f"signal {name}: not a number in the {role}") from None
    if values.ndim != 1:
        raise IncomparableError(f"signal {name}: a list per message, not one number")
    return Series(arrays["log_time_ns"], values)


def _from(signal: Series, offset: tuple[float, float] | None, role: int) -> Series:
    """``signal`` less its run's start (``offset``'s ``role``-th), when it has one."""
    return signal if offset is None else Series(signal.t_ns, signal.values - offset[role])


def _from_first_tick(signals: list[Series], data: SessionData) -> tuple[list[Series], int]:
    """Session time: the signals' log times from the first of them (the first tick; events
    and set-up before it do not shift a real-time session against a lockstep one), else from
    the session's first message; and that origin [ns]."""
    firsts = [int(s.t_ns[0]) for s in signals if s.t_ns.size]
    span = data.time_range_ns()
    start = min(firsts) if firsts else (span[0] if span else 0)
    return [Series(s.t_ns - start, s.values) for s in signals], start


def _signal_row(name: str, ours: Series, theirs: Series, tolerance: Tolerance,
                lockstep: bool, notes: list[str]) -> Row:
    aligned: Aligned = (tick_for_tick if lockstep else interpolated)(ours, theirs)
    if aligned.t_s.size == 0:
        raise IncomparableError(f"signal {name}: the two sessions share no tick of it")
    if aligned.t_s.size < max(ours.t_ns.size, theirs.t_ns.size):
        notes.append(f"{name}: compared over {aligned.t_s.size} ticks "
                     f"({aligned.t_s[0]:.4f}..{aligned.t_s[-1]:.4f} s); the baseline has "
                     f"{ours.t_ns.size}, the candidate {theirs.t_ns.size}")
    verdict = judge_signal(tolerance, aligned, ours)
    i = verdict.index
    return Row("signal", name, float(aligned.baseline[i]), float(aligned.candidate[i]),
               verdict.difference, tolerance.text(name), verdict.passed,
               round(float(aligned.t_s[i]), 9))
