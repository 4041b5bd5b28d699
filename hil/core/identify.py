"""Signals of a recorded session for N4SID identification, and model files.

Signals are named ``TOPIC:FIELD``. FIELD is a path into the JSON message: keys joined by
``.``, list elements as ``[N]`` (from 0). Examples::

    /bench/power:L2            message {"L2": 431.2, ...}
    /bench/power:va.L2         message {"va": {"L1": 0.0, "L2": 431.2}}
    /bench/relays:coils[2]     message {"coils": [false, false, true, ...]}
    /bench/power:phases[1].va  message {"phases": [{"va": 0.0}, {"va": 431.2}]}

The signal is split at its last ``:`` (a topic may contain ``:``, a field may not). Booleans
count as 0/1. All signals are resampled on the time stamps of the first output with a
zero-order hold (each input keeps the value of its latest message at or before the output's
stamp); output samples before every signal has a value are dropped.

The model file (JSON, see :func:`hil.controllers.ident.model_file.model_to_dict`) records the
command that produced it; :func:`load_model_file` reads it back for the controllers' configs.
"""

from __future__ import annotations

import json
import math
import os
import re
import shlex
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil.controllers.ident.model_file import dumps_model, loads_model
from hil.controllers.ident.n4sid import IdentificationError, IdentifiedModel
from hil.core.recording.reader import SessionData
from hil.errors import ConfigError, UsageError

IRREGULAR_TOLERANCE = 0.25  # an output interval off the median by more than this is irregular


@dataclass(frozen=True)
class SignalSpec:
    """A parsed ``TOPIC:FIELD``."""

    text: str
    topic: str
    path: tuple[str | int, ...]


# -- signals --------------------------------------------------------------------------------

_KEY = re.compile(r"[^.\[\]]+")
_INDEX = re.compile(r"\[(\d+)\]")


def parse_signal(text: str) -> SignalSpec:
    """``TOPIC:FIELD`` -> SignalSpec; a malformed one raises UsageError naming it."""
    topic, sep, field = text.rpartition(":")
    if not sep or not topic or not field:
        raise UsageError(f"signal {text!r}: expected TOPIC:FIELD, e.g. /bench/power:L2")
    path: list[str | int] = []
    pos = 0
    while pos < len(field):
        index = _INDEX.match(field, pos)
        if index:
            path.append(int(index.group(1)))
            pos = index.end()
            continue
        key_start = pos + 1 if path else pos
        if path and field[pos] != ".":
            break
        key = _KEY.match(field, key_start)
        if not key:
            break
        path.append(key.group(0))
        pos = key.end()
    if pos != len(field) or not path:
        raise UsageError(
            f"signal {text!r}: bad field path {field!r} at character {pos + 1}; use keys "
            "joined by '.' and list elements as [N], e.g. phases[1].va"
        )
    return SignalSpec(text, topic, tuple(path))


def extract_signal(
    data: SessionData, spec: SignalSpec, t0_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """(log_time_ns, values) of one signal; every problem raises UsageError naming it."""
    messages = data.topic(spec.topic)
    if not messages:
        known = ", ".join(t for t in sorted(data.messages) if data.messages[t]) or "none"
        raise UsageError(f"{spec.text}: unknown topic {spec.topic!r} (or no messages in it); "
                         f"topics with messages: {known}")
    times = np.fromiter((t for t, _ in messages), dtype=np.int64, count=len(messages))
    values = np.empty(len(messages))
    for k, (t, message) in enumerate(messages):
        node, reason = _walk(message, spec.path)
        if reason:
            where = (f"in {spec.topic}" if k == 0 else
                     f"in message {k} of {spec.topic} (t = {(t - t0_ns) / 1e9:.3f} s)")
            raise UsageError(f"{spec.text}: {reason} {where}")
        if node is None:
            node = math.nan
        if isinstance(node, bool):
            node = float(node)
        if not isinstance(node, (int, float)):
            raise UsageError(f"{spec.text}: is a {type(node).__name__}, not a number "
                             f"(message {k} of {spec.topic}); pick an element with [N] or .KEY")
        values[k] = node
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        k = int(bad[0])
        raise UsageError(
            f"{spec.text}: {bad.size} NaN/missing value(s) in the log, first at "
            f"t = {(times[k] - t0_ns) / 1e9:.3f} s (message {k} of {len(values)}); "
            "identification needs complete data: cut the record or fix the logger"
        )
    return times, values


def aligned_signals(
    data: SessionData, inputs: list[SignalSpec], outputs: list[SignalSpec]
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Inputs and outputs on the first output's time stamps (zero-order hold).

    Returns (u, y, dt, irregular interval count).
    """
    span = data.time_range_ns()
    t0 = span[0] if span else 0
    series = [extract_signal(data, spec, t0) for spec in inputs + outputs]
    grid = series[len(inputs)][0]
    picks = [np.searchsorted(times, grid, side="right") - 1 for times, _ in series]
    first = max(int(np.searchsorted(idx, 0)) for idx in picks)  # idx is non-decreasing
    if grid.size - first < 2:
        raise UsageError(f"{outputs[0].text}: fewer than 2 output samples after every signal "
                         "has started; nothing to identify")
    columns = [values[idx[first:]] for (_, values), idx in zip(series, picks, strict=True)]
    grid = grid[first:]
    steps = np.diff(grid)
    dt_ns = float(np.median(steps))
    if dt_ns <= 0:
        raise UsageError(f"{outputs[0].text}: time stamps do not advance (median step "
                         f"{dt_ns:g} ns)")
    irregular = int(np.sum(np.abs(steps - dt_ns) > IRREGULAR_TOLERANCE * dt_ns))
    u = np.column_stack(columns[: len(inputs)])
    y = np.column_stack(columns[len(inputs):])
    return u, y, dt_ns / 1e9, irregular


def describe_signals(data: SessionData) -> str:
    """One line listing the numeric fields of each topic (for error messages)."""
    parts = []
    for topic, messages in sorted(data.messages.items()):
        if topic == "/events" or topic.startswith("/loop/") or not messages:
            continue
        fields = sorted(_numeric_paths(messages[0][1]))
        if fields:
            shown = ", ".join(fields[:12]) + (", ..." if len(fields) > 12 else "")
            parts.append(f"{topic}: {shown}")
    return "signals in this file: " + ("; ".join(parts) if parts else "none")


def _walk(message: Any, path: tuple[str | int, ...]) -> tuple[Any, str]:
    node = message
    for depth, step in enumerate(path):
        here = _format_path(path[:depth]) or "the message"
        if isinstance(step, int):
            if not isinstance(node, list):
                return None, f"{here} is not a list, [{step}] does not apply"
            if step >= len(node):
                return None, f"index [{step}] out of range ({here} has {len(node)} elements)"
            node = node[step]
        else:
            if not isinstance(node, dict):
                return None, f"{here} is not an object, .{step} does not apply"
            if step not in node:
                keys = ", ".join(sorted(node)) or "none"
                return None, f"unknown field {step!r} (fields of {here}: {keys})"
            node = node[step]
    return node, ""


def _format_path(path: tuple[str | int, ...]) -> str:
    text = ""
    for step in path:
        text += f"[{step}]" if isinstance(step, int) else (f".{step}" if text else step)
    return text


def _numeric_paths(node: Any, prefix: str = "") -> list[str]:
    if isinstance(node, bool | int | float):
        return [prefix]
    if isinstance(node, dict):
        return [p for key, value in node.items()
                for p in _numeric_paths(value, f"{prefix}.{key}" if prefix else str(key))]
    if isinstance(node, list):
        return [p for k, value in enumerate(node) for p in _numeric_paths(value, f"{prefix}[{k}]")]
    return []


# -- model files ------------------------------------------------------------------------------


def save_model_file(path: str | os.PathLike[str], model: IdentifiedModel) -> None:
    """Write the model file atomically (a reader never sees half a file)."""
    path = os.fspath(path)
    tmp = f"{path}.tmp"
    try:
        directory = os.path.dirname(os.path.abspath(path))
        os.makedirs(directory, exist_ok=True)
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(dumps_model(model))
        os.replace(tmp, path)
    except OSError as exc:
        raise UsageError(f"cannot write model file {path}: {exc.strerror or exc}") from None


def load_model_file(path: str | os.PathLike[str]) -> IdentifiedModel:
    """Read a model file written by ``hil identify``; problems raise ConfigError naming it."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except OSError as exc:
        raise ConfigError(f"model file {path}: {exc.strerror or exc}") from None
    try:
        return loads_model(text)
    except IdentificationError as exc:
        raise ConfigError(f"model file {path}: {exc}") from None


# -- presentation ----------------------------------------------------------------------------


def experiment_command(data: SessionData) -> str:
    """The command line that recorded the session (``hil ...``), or "" if it is not known."""
    try:
        argv = json.loads(data.metadata.get("session", {}).get("argv", ""))
    except ValueError:
        return ""
    if not isinstance(argv, list) or not argv:
        return ""
    argv = [str(arg) for arg in argv]
    if os.path.basename(argv[0]) in ("hil", "__main__.py"):  # the console script, python -m hil
        argv[0] = "hil"
    return shlex.join(argv)
