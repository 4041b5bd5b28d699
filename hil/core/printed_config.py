"""``--print-config``'s text: the settings of a run as a TOML config file that ``--config``
takes back as it is, so the printed file runs the same run.

Every key of the configs is written under its table, with its origin as a comment; a key no
layer set and whose reader has no value for it (``increments_per_rev``: the drive's own) is
written commented out, as the packaged files do. The run's options (``run.*``) are flags, not
keys: they are written as comments, with the command line that runs the printed file again.
"""

from __future__ import annotations

import json
import math
import re
import shlex
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

from hil.core.settings import Setting

#: where a key's origin comment starts
COMMENT_COLUMN = 46
#: the options that no flag of the command line gives back as it is (a labgrid place: its
#: resources, which ``--place NAME`` sets)
NOT_FLAGS = ("run.lab",)
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")
_IN_ARRAY = re.compile(r"^([^.\[]+)\[(\d+)\]\.(.+)$")


def format_settings(title: str, settings: Sequence[Setting]) -> str:
    """The settings as a config file: a header, the run's options as comments (with the
    command line that runs the file again), then every key under its table."""
    options = [s for s in settings if s.key.startswith("run.")]
    keys = [s for s in settings if not s.key.startswith("run.")]
    command = title.split(":")[0]
    lines = [f"# {title}: each value as it runs, and where it came from.",
             f"# A config file: '{command} --config FILE' takes it back as it is."]
    if options:
        lines += ["# The run's options are flags, not keys; the same run again:",
                  f"#   {command_line(command, options)}", "#"]
        lines += ["# " + line for line in _key_lines(options, "run.", quoted=False)]
    return "\n".join([*lines, *_tables(keys)]).rstrip() + "\n"


def command_line(command: str, options: Sequence[Setting]) -> str:
    """``command --config FILE`` and the flags that gave the run's options (those whose
    origin is a flag)."""
    words = [*command.split(), "--config", "FILE"]
    for setting in options:
        if setting.origin.startswith("--") and setting.key not in NOT_FLAGS:
            words += _flag_words(setting.origin.split()[0], setting.value)
    return " ".join(shlex.quote(word) if word != "FILE" else word for word in words)


def _flag_words(flag: str, value: Any) -> list[str]:
    """The words that give ``value`` with ``flag`` (a list or a table: one flag each)."""
    if value is None or value is False:
        return []
    if value is True:
        return [flag]
    if isinstance(value, (list, tuple)):
        return [word for item in value for word in (flag, _word(item))]
    if isinstance(value, Mapping):  # --param K=V, --topic-encoding T=E...; --params: the file
        return [] if flag == "--params" else \
            [word for k, v in value.items() for word in (flag, f"{k}={_word(v)}")]
    return [flag, _word(value)]


def _word(value: Any) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    return repr(value) if isinstance(value, float) else str(value)


def _tables(settings: Sequence[Setting]) -> list[str]:
    """The keys under their tables: the top level's first, then each table once, in the order
    its first key came (a table before its sub-tables)."""
    settings = _with_arrays_resolved(settings)
    heads: dict[str, list[tuple[str, Setting]]] = {}
    for head, name, setting in _placed(settings):
        heads.setdefault(head, []).append((name, setting))
    lines = []
    for head in sorted(heads, key=lambda h: h != ""):  # stable: the top level first
        lines += ["", f"[{head}]"] if head else [""]
        for name, setting in heads[head]:
            lines += _key_lines([setting], name=name)
    return lines


def _placed(settings: Sequence[Setting]) -> Iterator[tuple[str, str, Setting]]:
    """Each setting's table (a TOML header) and key. A ``[limits]`` entry's KPI may hold
    dots (``step_us.p99``): its bounds become one inline table under the KPI's quoted name."""
    limits: dict[str, dict[str, Any]] = {}
    for setting in settings:
        if _IN_ARRAY.match(setting.key):  # in an array of tables: written with the array
            continue
        if setting.key.startswith("limits."):
            kpi, _, bound = setting.key.removeprefix("limits.").rpartition(".")
            if kpi not in limits:
                limits[kpi] = {}
                yield "limits", kpi, Setting(f"limits.{kpi}", limits[kpi], setting.origin)
            limits[kpi][bound] = setting.value
            continue
        parts = setting.key.split(".")
        yield ".".join(_key(part) for part in parts[:-1]), parts[-1], setting


def _with_arrays_resolved(settings: Sequence[Setting]) -> list[Setting]:
    """An array of tables (``axis``) with the values its readers resolved laid over the raw
    ones (``axis[0].eds``: the path from the file that named it)."""
    read = {s.key: s.value for s in settings if _IN_ARRAY.match(s.key)}
    out = []
    for setting in settings:
        if isinstance(setting.value, list) and any(k.startswith(setting.key + "[")
                                                   for k in read):
            items = [dict(item) if isinstance(item, Mapping) else item for item in setting.value]
            for key, value in read.items():
                name, index, sub = _IN_ARRAY.match(key).groups()  # type: ignore[union-attr]
                item = items[int(index)] if name == setting.key else None
                if isinstance(item, dict) and "." not in sub and value is not None:
                    item[sub] = value
            setting = Setting(setting.key, items, setting.origin, setting.kind, setting.rule)
        out.append(setting)
    return out


def _key_lines(settings: Sequence[Setting], prefix: str = "", name: str | None = None,
               quoted: bool = True) -> list[str]:
    """``key = value`` lines, each with its origin as a comment; a key without a value
    commented out (``quoted``: keys as TOML writes them, else as the settings name them)."""
    lines = []
    for setting in settings:
        key = name if name is not None else setting.key.removeprefix(prefix)
        key = _key(key) if quoted else key
        if setting.value is None:
            line = f"# {key} (not set)" if quoted else f"{key} (not set)"
        else:
            line = f"{key} = {toml_value(setting.value)}"
        lines.append(f"{line.ljust(COMMENT_COLUMN)} # {setting.origin}")
    return lines


def _key(name: str) -> str:
    """A TOML key: bare when it can be, else quoted."""
    return name if _BARE_KEY.fullmatch(name) else json.dumps(name, ensure_ascii=False)


def toml_value(value: Any) -> str:
    """``value`` as TOML: tables and arrays inline; None is no TOML value (left out)."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return repr(value) if math.isfinite(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, Mapping):
        items = [f"{_key(str(k))} = {toml_value(v)}" for k, v in value.items() if v is not None]
        return "{ " + ", ".join(items) + " }" if items else "{}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise TypeError(f"{value!r} has no TOML form")
