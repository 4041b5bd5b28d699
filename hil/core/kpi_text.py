"""KPIs as a person reads them, wherever hil writes them as text (``hil report``, a run's
summary, the KPI table of a report's PNG): numbers to four significant digits without an
exponent in the usual range (``0.0679``, ``536.6``, ``22760``), yes / no for a flag, a group
of figures on one line (``median 11.08, p99 1268, max 22760``), a limit as its verdict, a fit
as ``99.97 %`` (:func:`fit_text`). The ``--json`` documents keep every digit."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

#: significant digits of a number written for a person
DIGITS = 4
#: decimals of a fit [%]
FIT_DECIMALS = 2


def number_text(value: float) -> str:
    """``value`` to :data:`DIGITS` significant digits, without an exponent between 1e-3 and
    1e9 (an integral value whole: ``12000``, not ``1.2e+04``)."""
    if not math.isfinite(value):
        return str(value)
    if value == int(value) and abs(value) < 1e15:
        return str(int(value))
    size = abs(value)
    if not 1e-3 <= size < 1e9:
        return f"{value:.{DIGITS - 1}e}"
    decimals = max(0, DIGITS - 1 - math.floor(math.log10(size)))
    text = f"{value:.{decimals}f}"
    return text.rstrip("0").rstrip(".") if "." in text else text


def fit_text(pct: float) -> str:
    """A fit [%] (``hil identify``, ``hil twin check``: its text, its PNG) to
    :data:`FIT_DECIMALS` decimals, cut toward minus infinity so that a fit short of 100 % never
    reads as 100 % (99.996 is ``99.99 %``; only an exact twin is ``100.00 %``)."""
    if not math.isfinite(pct):
        return f"{pct} %"
    scale = 10**FIT_DECIMALS
    return f"{math.floor(round(pct * scale, 6)) / scale:.{FIT_DECIMALS}f} %"


def value_text(value: Any) -> str:
    """One KPI's value: a number (:func:`number_text`), yes / no, ``-`` for none, a group of
    figures as ``name value, ...``, a list as its items."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int | float):
        return number_text(float(value))
    if isinstance(value, Mapping):
        return ", ".join(f"{key} {value_text(item)}" for key, item in value.items()) or "-"
    if isinstance(value, list | tuple):
        return "; ".join(value_text(item) for item in value) or "-"
    return str(value)


def limit_text(row: Mapping[str, Any]) -> str:
    """A judged limit (a ``limits`` row): ``rms_error_deg<=0.5: measured 0.3 (holds)``."""
    verdict = "holds" if row.get("passed") else "VIOLATED"
    return f"{row.get('limit')}: measured {value_text(row.get('measured'))} ({verdict})"


def kpi_rows(kpis: Mapping[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    """The KPIs as (name, text) rows: a group of figures on one row, a group of groups (an
    axis' KPIs) as ``group.name`` rows, each judged limit on a ``limit`` row."""
    rows: list[tuple[str, str]] = []
    for key, value in kpis.items():
        name = f"{prefix}{key}"
        if key == "limits" and isinstance(value, list):
            rows += [("limit", limit_text(row) if isinstance(row, Mapping) else str(row))
                     for row in value]
        elif isinstance(value, Mapping) and any(isinstance(v, Mapping) for v in value.values()):
            rows += kpi_rows(value, f"{name}.")
        else:
            rows.append((name, value_text(value)))
    return rows
