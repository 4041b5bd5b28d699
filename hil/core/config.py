"""Configuration files (TOML): loading with errors that name the file, line and key."""

from __future__ import annotations

import copy
import math
import os
from collections.abc import Mapping
from typing import Any, overload

from hil.core.errors import ConfigError

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]


#: what a config may be: no hil config comes near either bound
MAX_CONFIG_BYTES = 4 << 20
MAX_CONFIG_DEPTH = 16


def parse_toml(text: str, source: str) -> dict[str, Any]:
    """Parse TOML text; a syntax error becomes a ConfigError naming ``source`` and the line,
    and so does a text no config can be (larger than :data:`MAX_CONFIG_BYTES`, tables or
    arrays nested deeper than :data:`MAX_CONFIG_DEPTH`), before it costs a recursion or
    memory error."""
    if len(text) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{source}: {len(text)} characters: larger than any config "
                          f"({MAX_CONFIG_BYTES >> 20} MiB at most)")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: invalid TOML: {exc}") from None
    except (RecursionError, MemoryError):
        raise ConfigError(f"{source}: nested too deeply to be a config (at most "
                          f"{MAX_CONFIG_DEPTH} levels)") from None
    if _depth(data) > MAX_CONFIG_DEPTH:
        raise ConfigError(f"{source}: nested too deeply to be a config (at most "
                          f"{MAX_CONFIG_DEPTH} levels)")
    return data


def _depth(value: Any) -> int:
    """How deep tables and arrays nest in ``value`` (counted without recursion)."""
    deepest, stack = 0, [(value, 0)]
    while stack:
        item, level = stack.pop()
        if isinstance(item, dict):
            children: Any = item.values()
        elif isinstance(item, list):
            children = item
        else:
            continue
        deepest = max(deepest, level + 1)
        if deepest > MAX_CONFIG_DEPTH:
            return deepest
        stack.extend((child, level + 1) for child in children)
    return deepest


def load_toml(path: str | os.PathLike[str]) -> tuple[dict[str, Any], str]:
    """Read a TOML file; return (parsed dict, original text)."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read config file: {exc}") from None
    return parse_toml(text, path), text


def deep_merge(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``override`` laid over it, tables merged key by key (inputs untouched)."""
    merged = copy.deepcopy(dict(base))
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


_MISSING: Any = object()


class Table:
    """One TOML table read strictly: every key is read with its type and range, and
    :meth:`done` refuses the keys nobody read, since a misspelt key would otherwise fall back to
    its default without a word. Errors name the file (``source``) and the dotted key.

    Typical use, in an application's config module::

        t = Table(raw, "bench.toml")
        bus = t.table("bus")
        timeout = bus.number("timeout_s", 0.1, above=0)
        bus.done()
        t.done()
    """

    def __init__(self, data: Mapping[str, Any], source: str, path: str = "") -> None:
        if not isinstance(data, Mapping):
            where = f"'{path}'" if path else "the file"
            raise ConfigError(f"{source}: {where} must be a table, got {type(data).__name__}")
        self.data = data
        self.source = source
        self.path = path
        self._read: set[str] = set()

    def key(self, name: str) -> str:
        """The dotted key of ``name`` in this table, as errors name it."""
        return f"{self.path}.{name}" if self.path else name

    def error(self, name: str, problem: str) -> ConfigError:
        """A ConfigError about key ``name``: ``"<source>: key 'a.b' <problem>"``."""
        return ConfigError(f"{self.source}: key '{self.key(name)}' {problem}")

    def __contains__(self, name: str) -> bool:
        return name in self.data

    def names(self) -> list[str]:
        """The keys present, in file order (for tables keyed by name, e.g. ``[relays]``)."""
        return list(self.data)

    def raw(self, name: str, default: Any = _MISSING) -> Any:
        """The value of ``name`` unchecked (marks it read)."""
        self._read.add(name)
        if name not in self.data:
            if default is _MISSING:
                raise ConfigError(f"{self.source}: missing key '{self.key(name)}'")
            return default
        return self.data[name]

    def get(self, name: str, kind: type | tuple[type, ...], default: Any = _MISSING) -> Any:
        """``name`` checked against ``kind`` (``bool`` never passes for a number; an int
        passes for a float and is converted)."""
        if name not in self.data and default is not _MISSING:
            self._read.add(name)
            return default
        value = self.raw(name)
        kinds = kind if isinstance(kind, tuple) else (kind,)
        if float in kinds and int not in kinds:
            kinds = (*kinds, int)
        if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
            names = " or ".join(k.__name__ for k in kinds)
            raise self.error(name, f"must be {names}, got {type(value).__name__} {value!r}")
        if kinds[0] is float and isinstance(value, int | float):
            return float(value)
        return value

    @overload
    def number(self, name: str, default: None, *, above: float | None = None,
               at_least: float | None = None, at_most: float | None = None) -> float | None: ...

    @overload
    def number(self, name: str, default: float = ..., *, above: float | None = None,
               at_least: float | None = None, at_most: float | None = None) -> float: ...

    def number(self, name: str, default: Any = _MISSING, *, above: float | None = None,
               at_least: float | None = None, at_most: float | None = None) -> float | None:
        """A finite float, optionally ``> above``, ``>= at_least``, ``<= at_most``; a None
        default makes the key optional."""
        value = self.get(name, float, default)
        if value is None:
            return None
        _check_range(self, name, value, above, at_least, at_most)
        return float(value)

    @overload
    def integer(self, name: str, default: None, *, above: int | None = None,
                at_least: int | None = None, at_most: int | None = None) -> int | None: ...

    @overload
    def integer(self, name: str, default: int = ..., *, above: int | None = None,
                at_least: int | None = None, at_most: int | None = None) -> int: ...

    def integer(self, name: str, default: Any = _MISSING, *, above: int | None = None,
                at_least: int | None = None, at_most: int | None = None) -> int | None:
        """An int, optionally ``> above``, ``>= at_least``, ``<= at_most``; a None default
        makes the key optional."""
        value = self.get(name, int, default)
        if value is None:
            return None
        _check_range(self, name, value, above, at_least, at_most)
        return int(value)

    def string(self, name: str, default: Any = _MISSING, *,
               choices: tuple[str, ...] | None = None) -> str:
        """A string, optionally one of ``choices``."""
        value = self.get(name, str, default)
        if choices is not None and value not in choices:
            raise self.error(name, f"must be one of {', '.join(choices)}, got {value!r}")
        return str(value)

    def boolean(self, name: str, default: Any = _MISSING) -> bool:
        return bool(self.get(name, bool, default))

    def table(self, name: str, *, required: bool = False) -> Table:
        """The sub-table ``name`` (an empty one when absent, unless ``required``)."""
        value = self.raw(name, _MISSING if required else {})
        if not isinstance(value, Mapping):
            raise self.error(name, f"must be a table, got {type(value).__name__} {value!r}")
        return Table(value, self.source, self.key(name))

    def done(self) -> None:
        """Refuse every key of this table that was not read."""
        unknown = [name for name in self.data if name not in self._read]
        if unknown:
            known = ", ".join(sorted(self._read)) or "none"
            raise ConfigError(f"{self.source}: unknown key '{self.key(unknown[0])}' "
                              f"(known here: {known})")


def _check_range(table: Table, name: str, value: float, above: float | None,
                 at_least: float | None, at_most: float | None) -> None:
    if not math.isfinite(value):
        raise table.error(name, f"must be a finite number, got {value!r}")
    if above is not None and not value > above:
        raise table.error(name, f"must be > {above:g}, got {value:g}")
    if at_least is not None and not value >= at_least:
        raise table.error(name, f"must be >= {at_least:g}, got {value:g}")
    if at_most is not None and not value <= at_most:
        raise table.error(name, f"must be <= {at_most:g}, got {value:g}")
