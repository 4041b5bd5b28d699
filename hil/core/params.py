"""``--param KEY=VALUE`` for a plug-in controller: numbers parsed as numbers."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from hil.errors import UsageError

ParamValue = int | float | bool | str


def parse_value(text: str) -> ParamValue:
    """``3`` -> 3, ``0.5`` / ``1e-3`` -> float, ``true``/``false`` -> bool, else the string."""
    lowered = text.strip().lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        return text
    return value if math.isfinite(value) else text


def parse_param(text: str) -> tuple[str, ParamValue]:
    """``'gain=2.5'`` -> ("gain", 2.5), ``'y.gain=2'`` (axis y's, with ``--axes``) ->
    ("y.gain", 2); a UsageError names a malformed one."""
    key, sep, value = text.partition("=")
    key = key.strip()
    parts = key.split(".")
    if not sep or len(parts) > 2 or not all(part.isidentifier() for part in parts):
        raise UsageError(f"--param {text!r}: expected KEY=VALUE with KEY a name, e.g. "
                         "gain=2.5 (AXIS.KEY with --axes)")
    return key, parse_value(value.strip())


def merge_params(table: Mapping[str, Any], flags: Iterable[str]) -> dict[str, Any]:
    """The ``[controller]`` table of the config with the ``--param`` flags laid over it."""
    params = dict(table)
    params.update(parse_param(text) for text in flags)
    return params
