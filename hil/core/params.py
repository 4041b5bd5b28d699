"""``--param KEY=VALUE`` for a plug-in controller: numbers parsed as numbers; ``--params F.toml``
for many at once (a sweep's ``best.toml``)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from hil.core.config import load_toml
from hil.errors import ConfigError, UsageError

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


def read_params_file(path: str) -> dict[str, ParamValue]:
    """``--params F.toml``: the controller's parameters, ``NAME = VALUE`` each (a number,
    true/false or text), an axis' own in its table (``[x]`` ``gain = 2`` is ``x.gain``)."""
    data, _ = load_toml(path)
    params: dict[str, ParamValue] = {}
    for key, value in data.items():
        entries = value.items() if isinstance(value, dict) else [("", value)]
        for sub, item in entries:
            name = f"{key}.{sub}" if sub else key
            if isinstance(item, dict) or not isinstance(item, (bool, int, float, str)):
                shown = name if name.isprintable() else repr(name)  # one line, whatever the key
                raise ConfigError(f"{path}: {shown}: a parameter is a number, true/false or "
                                  f"text (an axis' own in its [AXIS] table), got {item!r:.40}")
            params[name] = item
    return params


def params_origin(params: Mapping[str, Any], params_file: str | None) -> str:
    """Where a run's controller parameters came from, for ``--print-config``: ``--params``
    when the file gave them all, else ``--param``."""
    if params_file is None:
        return "--param"
    given = read_params_file(params_file)
    return "--params" if all(k in given and given[k] == v for k, v in params.items()) \
        else "--param"
