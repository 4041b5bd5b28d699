"""Regression against a baseline: a candidate session held against a baseline session, KPI by
KPI and signal by signal, each within its tolerance (``hil compare``, the ``hil_baseline``
pytest fixture)."""

from hil.compare.comparison import (
    Comparison,
    IncomparableError,
    Row,
    compare_data,
    compare_sessions,
)
from hil.compare.tolerances import Tolerance, parse_tolerance, tolerances_file

__all__ = ["Comparison", "IncomparableError", "Row", "Tolerance", "compare_data",
           "compare_sessions", "parse_tolerance", "tolerances_file"]
