"""A run's KPIs as a dataclass: one source for the names a ``--limit`` may use, the ``--json``
document and the JUnit properties (:func:`hil.core.verdict.kpi_properties` flattens the
document).

An application declares its KPI document as a subclass of :class:`Kpis`, one field per key in
the order the document lists them, each made with :func:`kpi`: ``key`` when the document's
spelling is not a Python name (``peak_current_mA`` for the field ``peak_current_ma``),
``limit=False`` for context a limit may not name (the controller, the session's path),
``optional=True`` for a key left out of the document when it is None (an MPC's horizons). A
field holding another :class:`Kpis` (one axis' KPIs) or a mapping of them is a group: a limit
names its keys as ``GROUP.KEY``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, TypeVar

K = TypeVar("K", bound="Kpis")


def kpi(default: Any = None, *, key: str | None = None, limit: bool = True,
        optional: bool = False) -> Any:
    """A field of a :class:`Kpis` (see the module)."""
    return dataclasses.field(default=default,
                             metadata={"key": key, "limit": limit, "optional": optional})


@dataclasses.dataclass
class Kpis:
    """Base of a KPI document (see the module)."""

    @classmethod
    def limit_names(cls) -> tuple[str, ...]:
        """The keys a ``--limit`` may name (a group by its key)."""
        return tuple(_key(f) for f in dataclasses.fields(cls) if f.metadata.get("limit", True))

    def lay(self: K, part: Kpis) -> K:
        """These KPIs with ``part``'s fields (the same names) laid in; returns self."""
        for f in dataclasses.fields(part):
            setattr(self, f.name, getattr(part, f.name))
        return self

    def document(self) -> dict[str, Any]:
        """The ``--json`` document: every field under its key, groups as nested documents,
        optional fields left out while None."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value is None and f.metadata.get("optional"):
                continue
            out[_key(f)] = _document(value)
        return out


def _key(f: dataclasses.Field[Any]) -> str:
    return f.metadata.get("key") or f.name


def _document(value: Any) -> Any:
    if isinstance(value, Kpis):
        return value.document()
    if isinstance(value, Mapping):
        return {name: _document(item) for name, item in value.items()}
    return value
