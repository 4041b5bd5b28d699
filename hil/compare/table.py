"""A comparison as text: the table of rows, its notes, and one summary line."""

from __future__ import annotations

from hil.compare.comparison import Comparison, Row

#: after the name of a position taken relative to each run's start
FROM_START = " (from start)"


def _number(value: float | None) -> str:
    return "-" if value is None else f"{value:.6g}"


def format_table(comparison: Comparison) -> str:
    """``kind name baseline candidate difference tolerance at-t verdict``, one row each (a
    position relative to each run's start marked ``(from start)``, the notes say where each
    started)."""
    names = [row.name + (FROM_START if row.from_start_deg else "") for row in comparison.rows]
    width = max([len(name) for name in names] + [4])
    lines = [f"baseline   {comparison.baseline}", f"candidate  {comparison.candidate}",
             f"{comparison.application} sessions, {comparison.alignment}",
             f"  {'kind':<6} {'name':<{width}} {'baseline':>12} {'candidate':>12} "
             f"{'difference':>12}  {'tolerance':<28} {'at t [s]':>9}  verdict"]
    for row, name in zip(comparison.rows, names, strict=True):
        at = "" if row.worst_t_s is None else f"{row.worst_t_s:.4f}"
        lines.append(f"  {row.kind:<6} {name:<{width}} {_number(row.baseline):>12} "
                     f"{_number(row.candidate):>12} {_number(row.difference):>12}  "
                     f"{row.tolerance:<28} {at:>9}  {'pass' if row.passed else 'FAIL'}")
    lines.extend(f"note: {note}" for note in comparison.notes)
    return "\n".join(lines)


def _outside(row: Row) -> str:
    unit = f" {row.unit}" if row.unit else ""
    where = "" if row.worst_t_s is None else f" at t = {row.worst_t_s:.4f} s"
    name = row.name + (FROM_START if row.from_start_deg else "")
    return f"{name} by {_number(row.difference)}{unit}{where} ({row.tolerance})"


def summary_line(comparison: Comparison) -> str:
    """``within tolerance: N KPIs and signals`` or what is outside, the worst signal first."""
    failed = comparison.failed()
    if not failed:
        return f"within tolerance: {len(comparison.rows)} KPI(s) and signal(s)"
    failed.sort(key=lambda row: row.kind != "signal")
    return (f"outside tolerance ({len(failed)} of {len(comparison.rows)}): "
            + "; ".join(_outside(row) for row in failed))
