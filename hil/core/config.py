"""Configuration files (TOML): loading with errors that name the file, line and key."""

from __future__ import annotations

import copy
import difflib
import math
import os
from collections.abc import Iterable, Mapping
from typing import Any, overload

from hil.core.settings import KeyRead, Layered
from hil.core.units import UNITS, implausible, unit_hint, written_with_unit
from hil.errors import ConfigError

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

    def __init__(self, data: Mapping[str, Any], source: str, path: str = "",
                 reads: list[KeyRead] | None = None, layered: Layered | None = None) -> None:
        if not isinstance(data, Mapping):
            where = f"'{path}'" if path else "the file"
            raise ConfigError(f"{source}: {where} must be a table, got {type(data).__name__}")
        self.data = data
        self.source = source
        self.path = path
        self.reads: list[KeyRead] = [] if reads is None else reads  # shared with sub-tables
        self.layered = layered  # who set each key: a flag is named in errors, paths resolved
        self._read: set[str] = set()

    def _note(self, name: str, value: Any, kind: str, rule: str = "") -> None:
        self.reads.append(KeyRead(self.key(name), value, kind, rule, name not in self.data))

    def key(self, name: str) -> str:
        """The dotted key of ``name`` in this table, as errors name it (a name with a line
        break or another control character escaped: an error stays one line)."""
        if not name.isprintable():
            name = name.encode("unicode_escape").decode("ascii")
        return f"{self.path}.{name}" if self.path else name

    def error(self, name: str, problem: str) -> ConfigError:
        """A ConfigError about key ``name``: ``"<source>: key 'a.b' <problem>"``, the source
        being the flag that set the key when a flag did."""
        key = self.key(name)
        origin = self.layered.origin(key) if self.layered is not None else ""
        source = origin if origin.startswith("-") and not origin.startswith("--config ") \
            else self.source
        return ConfigError(f"{source}: key '{key}' {problem}")

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

    def value(self, name: str, default: Any = _MISSING, kind: str = "any") -> Any:
        """The value of ``name`` unchecked here (its reader checks it), recorded as read."""
        value = self.raw(name, default)
        self._note(name, value, kind)
        return value

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
            unit = unit_of(name)
            if float in kinds and isinstance(value, str) and unit in UNITS \
                    and written_with_unit(value):  # '300 mA', '0.3A': the flags' words
                raise self.error(name, unit_hint(value, unit))
            asked = kind if isinstance(kind, tuple) else (kind,)
            names = " or ".join(_KIND_NAMES.get(k, k.__name__) for k in asked)
            raise self.error(name, f"must be {names}, got {_describe(value)}")
        if kinds[0] is float and isinstance(value, int | float):
            return float(value)
        return value

    @overload
    def number(self, name: str, default: None, *, above: float | None = None,
               at_least: float | None = None, at_most: float | None = None,
               plausible: tuple[float, str] | None = None) -> float | None: ...

    @overload
    def number(self, name: str, default: float = ..., *, above: float | None = None,
               at_least: float | None = None, at_most: float | None = None,
               plausible: tuple[float, str] | None = None) -> float: ...

    def number(self, name: str, default: Any = _MISSING, *, above: float | None = None,
               at_least: float | None = None, at_most: float | None = None,
               plausible: tuple[float, str] | None = None) -> float | None:
        """A finite float, optionally ``> above``, ``>= at_least``, ``<= at_most``; a None
        default makes the key optional. ``plausible``: (the smallest plausible value, the unit
        a smaller one was most likely written in), as the flag of the same value checks it
        (``current_limit_mA = 0.3``: amperes, as ``--umax 0.3``)."""
        value = self.get(name, float, default)
        self._note(name, value, "number", _rule(above, at_least, at_most) if plausible is None
                   else _rule(None, plausible[0], at_most))
        if value is None:
            return None
        _check_range(self, name, value, above, at_least, at_most)
        if plausible is not None and value < plausible[0]:
            raise self.error(name, f"= {value:g}: " + implausible(value, unit_of(name),
                                                                  *plausible))
        return float(value)

    @overload
    def integer(self, name: str, default: None, *, above: int | None = None,
                at_least: int | None = None, at_most: int | None = None,
                choices: tuple[int, ...] | None = None) -> int | None: ...

    @overload
    def integer(self, name: str, default: int = ..., *, above: int | None = None,
                at_least: int | None = None, at_most: int | None = None,
                choices: tuple[int, ...] | None = None) -> int: ...

    def integer(self, name: str, default: Any = _MISSING, *, above: int | None = None,
                at_least: int | None = None, at_most: int | None = None,
                choices: tuple[int, ...] | None = None) -> int | None:
        """An int, optionally ``> above``, ``>= at_least``, ``<= at_most`` or one of
        ``choices``; a None default makes the key optional."""
        value = self.get(name, int, default)
        rule = f"one of {', '.join(map(str, choices))}" if choices else ""
        self._note(name, value, "integer", rule or _rule(above, at_least, at_most))
        if value is None:
            return None
        _check_range(self, name, value, above, at_least, at_most)
        if choices is not None and value not in choices:
            raise self.error(name, f"must be one of {', '.join(map(str, choices))}, got {value}")
        return int(value)

    def string(self, name: str, default: Any = _MISSING, *,
               choices: tuple[str, ...] | None = None) -> str:
        """A string, optionally one of ``choices``."""
        value = self.get(name, str, default)
        self._note(name, value, "string", f"one of {', '.join(choices)}" if choices else "")
        if choices is not None and value not in choices:
            raise self.error(name, f"must be one of {', '.join(choices)}, got {value!r}")
        return str(value)

    def file_path(self, name: str, default: Any = _MISSING) -> str:
        """A file's path (``''``: none), relative to the folder of the config file that set
        it (a flag's: the working folder); recorded as resolved."""
        value = self.get(name, str, default)
        if value and self.layered is not None:
            value = self.layered.path(self.key(name), value)
        self._note(name, value, "path")
        return str(value)

    def boolean(self, name: str, default: Any = _MISSING) -> bool:
        value = bool(self.get(name, bool, default))
        self._note(name, value, "boolean")
        return value

    @overload
    def array(self, name: str, default: None, rule: str = "") -> list[Any] | None: ...

    @overload
    def array(self, name: str, default: list[Any] = ..., rule: str = "") -> list[Any]: ...

    def array(self, name: str, default: Any = _MISSING, rule: str = "") -> list[Any] | None:
        """An array (its items checked by the caller), recorded with ``rule``; a None default
        makes the key optional."""
        value = self.get(name, list, default)
        self._note(name, value, "array", rule)
        return None if value is None else list(value)

    def table(self, name: str, *, required: bool = False) -> Table:
        """The sub-table ``name`` (an empty one when absent, unless ``required``)."""
        value = self.raw(name, _MISSING if required else {})
        if not isinstance(value, Mapping):
            raise self.error(name, f"must be a table, got {_describe(value)}")
        return Table(value, self.source, self.key(name), self.reads, self.layered)

    def done(self) -> None:
        """Refuse every key of this table that was not read."""
        unknown = [name for name in self.data if name not in self._read]
        if unknown:
            close = closest(unknown[0], self._read)
            hint = f"did you mean '{self.key(close)}'? " if close else ""
            known = ", ".join(sorted(self._read)) or "none"
            raise ConfigError(f"{self.source}: unknown key '{self.key(unknown[0])}' "
                              f"({hint}known here: {known})")


def closest(name: str, known: Iterable[str]) -> str | None:
    """The known name ``name`` most likely misspells (the case aside first:
    ``current_limit_ma`` is ``current_limit_mA``), or None."""
    known = sorted(known)
    same = [k for k in known if k.lower() == name.lower()]
    if same:
        return same[0]
    close = difflib.get_close_matches(name, known, n=1, cutoff=0.75)
    return close[0] if close else None


_KIND_NAMES = {float: "a number", int: "an integer", str: "a string",
               bool: "a boolean (true or false)", list: "an array", dict: "a table"}


def _describe(value: Any) -> str:
    """A value as an error shows it, with its TOML kind: ``a string '300'``."""
    if isinstance(value, bool):
        return f"a boolean {str(value).lower()}"
    for kind, text in ((int, "an integer"), (float, "a number"), (str, "a string"),
                       (list, "an array"), (Mapping, "a table")):
        if isinstance(value, kind):
            return f"{text} {value!r:.60}"
    return f"{type(value).__name__} {value!r:.60}"


def _number(value: float) -> str:
    """A bound or a value as a person reads it: integers whole (``1000000``, not ``1e+06``)."""
    return str(value) if isinstance(value, int) else f"{value:g}"


def _rule(above: float | None, at_least: float | None, at_most: float | None) -> str:
    """The range a number is held to, as the reference shows it (``> 0, <= 32767``)."""
    parts = [f"{op} {_number(bound)}" for op, bound in ((">", above), (">=", at_least),
                                                         ("<=", at_most)) if bound is not None]
    return ", ".join(parts)


#: a key's unit, by the end of its name (the longest match wins)
UNIT_SUFFIXES = (("_mA_per_deg_s", "mA/(deg/s)"), ("_deg_s", "deg/s"), ("_per_s", "1/s"),
                 ("_permille", "per mille"), ("_mA", "mA"), ("_ms", "ms"), ("_us", "us"),
                 ("_s", "s"), ("_deg", "deg"), ("_va", "VA"), ("_VA", "VA"), ("_hz", "Hz"),
                 ("_v", "V"), ("_kwh", "kWh"), ("bitrate", "bit/s"))


def unit_of(key: str) -> str:
    """The unit of a key, from the end of its name (``current_limit_mA`` -> ``mA``); ``''``
    for a key without one."""
    name = key.rpartition(".")[2]
    return next((unit for suffix, unit in UNIT_SUFFIXES if name.endswith(suffix)), "")


def _check_range(table: Table, name: str, value: float, above: float | None,
                 at_least: float | None, at_most: float | None) -> None:
    unit = unit_of(name)
    unit = f" {unit}" if unit else ""
    if not math.isfinite(value):
        raise table.error(name, f"must be a finite number, got {value!r}")
    got = f"got {_number(value)}{unit}"
    if above is not None and not value > above:
        raise table.error(name, f"must be > {_number(above)}{unit}, {got}")
    if at_least is not None and not value >= at_least:
        raise table.error(name, f"must be >= {_number(at_least)}{unit}, {got}")
    if at_most is not None and not value <= at_most:
        raise table.error(name, f"must be <= {_number(at_most)}{unit}, {got}")
