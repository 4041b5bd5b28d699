"""Where each setting of a run comes from, in one order for every key:

    built-in defaults < the packaged config < the user's ``--config`` < flags

Each source is a :class:`Layer` of TOML-shaped tables; :func:`lay` lays them over each other and
remembers, for every key, the layer that set it last. An application reads the merged tables
strictly (:class:`hil.core.config.Table`, which records every key it reads and the rule it held
it to) and :func:`effective` joins the two: the value that runs, its kind, its rule and its origin,
which ``--print-config`` prints and the session records.

Safety and current limits only tighten from a flag: :func:`loosened` names the flags that would
loosen a limit of the layers below them, which a run refuses unless the user says so explicitly.
"""

from __future__ import annotations

import copy
import math
import os
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, fields, is_dataclass
from functools import cached_property, partial
from typing import Any

from hil.errors import UsageError

#: the origin of a key no layer set: the reading code's own default
BUILT_IN = "built-in default"


@dataclass(frozen=True)
class KeyRead:
    """One key as a :class:`Table` read it: its dotted name, the value the checks let through
    (the file's, or the code's default when ``defaulted``), its kind and the rule it was held to
    (``"> 0"``, ``"one of cst, csp"``...). A table's reads are what runs and what the
    configuration reference documents: one source."""

    key: str
    value: Any
    kind: str
    rule: str = ""
    defaulted: bool = False


@dataclass(frozen=True)
class Layer:
    """One source of settings: what it is called (``--config my.toml``, ``--umax``), the
    tables it sets, the tables it replaces whole rather than key by key (``whole``), and the
    folder its relative paths start from (None: the working folder)."""

    origin: str
    data: Mapping[str, Any]
    whole: tuple[str, ...] = ()
    folder: str | None = None


@dataclass(frozen=True)
class Layered:
    """Layers laid over each other: the merged tables and, per dotted key, the index of the
    layer that set it last (``origins``) in ``names`` (and ``folders``)."""

    data: dict[str, Any]
    origins: dict[str, int]
    names: tuple[str, ...]
    folders: tuple[str | None, ...] = ()

    def _setter(self, key: str) -> int | None:
        """The layer that set ``key`` last: a leaf's, a table's last-set leaf's, or for a key
        inside an array of tables (``axis[0].eds``) the array's, which a layer sets whole."""
        while key:
            if key in self._last_setters:
                return self._last_setters[key]
            key = key[:max(key.rfind("."), key.rfind("["), 0)]  # its parent: a table, an array
        return None

    @cached_property
    def _last_setters(self) -> dict[str, int]:
        """Per set key and per table holding one, the last layer that set it or a key in it
        (built once: a run's settings ask it of each of their keys)."""
        last: dict[str, int] = {}
        for dotted, index in self.origins.items():
            cut = len(dotted)
            while cut > 0:  # the key, then each table it is in
                last[dotted[:cut]] = max(index, last.get(dotted[:cut], index))
                cut = dotted.rfind(".", 0, cut)
        return last

    def origin(self, key: str) -> str:
        """Who set ``key`` (a leaf, or a table: its last-set leaf); :data:`BUILT_IN` if nobody."""
        index = self._setter(key)
        return BUILT_IN if index is None else self.names[index]

    def path(self, key: str, value: str) -> str:
        """``value``, a path set by ``key``, made absolute from the folder of the layer that set
        it (a config file's folder; a flag's: the working folder)."""
        if not value or os.path.isabs(value):
            return value
        index = self._setter(key)
        folder = self.folders[index] if index is not None else None
        return os.path.join(folder, value) if folder else os.path.abspath(value)

    def with_layer(self, layer: Layer) -> Layered:
        """These layers and ``layer`` over them."""
        data, origins = copy.deepcopy(self.data), dict(self.origins)
        _lay(data, layer.data, "", len(self.names), origins, layer.whole)
        return Layered(data, origins, (*self.names, layer.origin),
                       (*self.folders, layer.folder))


def lay(layers: Iterable[Layer]) -> Layered:
    """``layers`` laid over each other in order, tables merged key by key."""
    layered = Layered({}, {}, ())
    for layer in layers:
        layered = layered.with_layer(layer)
    return layered


def _lay(into: dict[str, Any], data: Mapping[str, Any], prefix: str, index: int,
         origins: dict[str, int], whole: tuple[str, ...]) -> None:
    for key, value in data.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, Mapping):
            if not isinstance(into.get(key), Mapping) or dotted in whole:
                _forget(origins, dotted, into.get(key))
                into[key] = {}
                if not value:  # an empty table laid whole is set, by this layer
                    origins[dotted] = index
            _lay(into[key], value, dotted + ".", index, origins, whole)
        else:
            _forget(origins, dotted, into.get(key))
            into[key] = copy.deepcopy(value)
            origins[dotted] = index


def _forget(origins: dict[str, int], key: str, replaced: Any) -> None:
    """A key replaced whole: its origin goes, and, when it held a table, the origins of what
    the table held (a value held none: no search of every key then)."""
    origins.pop(key, None)
    if isinstance(replaced, Mapping):
        for dotted in [d for d in origins if d.startswith(key + ".")]:
            del origins[dotted]


@dataclass(frozen=True)
class Setting:
    """One setting as it runs: its dotted key, value, kind and rule, and where it came from."""

    key: str
    value: Any
    origin: str
    kind: str = ""
    rule: str = ""

    def as_json(self) -> dict[str, Any]:
        return {"value": _plain(self.value), "origin": self.origin}


def effective(reads: Sequence[KeyRead], layered: Layered, prefix: str = "") -> list[Setting]:
    """The keys a reader read, each with the origin of its value (the last read of a key
    wins: a key read twice is one setting)."""
    by_key: dict[str, Setting] = {}
    for read in reads:
        origin = BUILT_IN if read.defaulted else layered.origin(read.key)
        by_key[read.key] = Setting(prefix + read.key, read.value, origin, read.kind, read.rule)
    order = {key: n for n, key in enumerate(_walk(layered.data))}

    def position(key: str) -> float:  # in the files' order; a key no file has, after its table
        head = key
        while head not in order and "." in head:
            head = head.rpartition(".")[0]
        return order.get(head, len(order)) + (0.0 if head == key else 0.5)

    return [by_key[key] for key in sorted(by_key, key=position)]


def _walk(data: Mapping[str, Any], prefix: str = "") -> Iterator[str]:
    """Every table and key of ``data``, dotted, in order."""
    for key, value in data.items():
        yield prefix + key
        if isinstance(value, Mapping):
            yield from _walk(value, f"{prefix}{key}.")


def option_settings(options: Any, defaults: Any, resolved: Mapping[str, tuple[Any, str]],
                    skip: Iterable[str], flag_of: Callable[[str], str]) -> list[Setting]:
    """The fields of an options dataclass as settings under ``run.``, but those in ``skip``: a
    field that differs from the same field of ``defaults`` came from its flag (``flag_of``).
    ``resolved`` gives fields whose value and origin were resolved elsewhere."""
    settings, nested = [], []
    for field in fields(options):
        if field.name in skip:
            continue
        value = getattr(options, field.name)
        if field.name in resolved:
            value, origin = resolved[field.name]
        else:
            same = value == getattr(defaults, field.name)
            origin = "default" if same else flag_of(field.name)
        if is_dataclass(value) and not isinstance(value, type):  # its fields, one by one
            flags: Mapping[str, str] = getattr(value, "FLAGS", {})
            inner = option_settings(value, getattr(defaults, field.name), {}, (),
                                    partial(_flag_in, flags))
            nested += [Setting(s.key.replace("run.", f"run.{field.name}.", 1), s.value,
                               s.origin) for s in inner]
            continue
        if callable(value):
            value = getattr(value, "__qualname__", repr(value))
        settings.append(Setting(f"run.{field.name}", _listed(value), origin))
    return settings + nested


def _flag_in(flags: Mapping[str, str], name: str) -> str:
    return flags.get(name, f"--{name}")


def _listed(value: Any) -> Any:
    if isinstance(value, tuple):
        return [str(item) for item in value]
    if isinstance(value, Mapping):
        return dict(value)
    return value


def _plain(value: Any) -> Any:
    """A value as JSON holds it (tuples as lists, infinities as strings)."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def settings_json(settings: Iterable[Setting]) -> dict[str, Any]:
    """``{key: {"value": ..., "origin": ...}}``: what ``--print-config --json`` prints."""
    return {s.key: s.as_json() for s in settings}


#: a limit's direction: an upper bound tightens downwards, a lower bound upwards, a switch on
UPPER, LOWER, SWITCH = "upper", "lower", "switch"


def loosened(before: Mapping[str, Any], after: Mapping[str, Any],
             directions: Mapping[str, str]) -> list[str]:
    """The keys of ``directions`` whose value in ``after`` is looser than in ``before``, as
    ``"key 45 -> 200"``."""
    found = []
    for key, direction in directions.items():
        old, new = before.get(key), after.get(key)
        if old is None or new is None or old == new:
            continue
        looser = (new > old if direction == UPPER else new < old if direction == LOWER
                  else bool(old) and not new)
        if looser:
            found.append(f"{key} {_text(old)} -> {_text(new)}")
    return found


class LooseningRefusedError(UsageError):
    """A flag that would loosen a configured limit, refused. Its text names the flag that lets
    it through (``--allow-looser-safety``, ``--allow-higher-current``); ``without_hatch`` is
    the refusal for a command that offers no such flag."""

    def __init__(self, refusal: str, hatch: str, without_hatch: str = "") -> None:
        super().__init__(refusal + hatch)
        self.without_hatch = refusal + without_hatch


def tightened_only(looser: Sequence[str], flag: str, allowed: bool
                   ) -> list[tuple[str, str]]:
    """A flag's limits that would be ``looser`` than the configured ones: refused (a
    :class:`LooseningRefusedError` naming the first) unless ``allowed``
    (``--allow-looser-safety``); then the warning notice the run records and prints."""
    if not looser:
        return []
    if not allowed:
        raise LooseningRefusedError(
            f"{flag} {looser[0]}: looser than the configured safety limit; a flag may tighten "
            "a limit, not loosen it", " (set it in the --config file, or add "
            "--allow-looser-safety, recorded)", " (set it in the --config file)")
    return [("safety.loosened", f"safety limits loosened by {flag}: {', '.join(looser)} "
             "(--allow-looser-safety)")]


def given_options(flags: Mapping[str, Any], known: Iterable[str],
                  renames: Mapping[str, str]) -> dict[str, Any]:
    """The options among ``flags`` (argparse dests, a sweep's values laid over them): each
    under its option name (``renames``: flag -> option where they differ); flags that are no
    option, and flags not given (None), left out."""
    names = set(known)
    given = {renames.get(flag, flag): value for flag, value in flags.items()}
    return {name: value for name, value in given.items()
            if name in names and value is not None}


def _text(value: Any) -> str:
    return str(value).lower() if isinstance(value, bool) else f"{value:g}"
