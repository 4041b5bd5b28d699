"""The parameter space of a sweep: ``--grid KEY=v1,v2``, ``--random N KEY=lo:hi`` and the
``[sweep]`` table, expanded into trials named by their parameters.

A KEY is a run option by its flag name (``ht``, ``gamma1``, ``prediction-every``) or a
controller parameter as ``param.NAME``. Values are converted and checked by the option's own
argparse type, so a bad one gets the same one-line error as on ``hil ... run``.
"""

from __future__ import annotations

import argparse
import itertools
import random
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from hil.core.params import parse_value
from hil.errors import UsageError

PARAM_PREFIX = "param."
UNSWEEPABLE = {"limit", "param", "help"}  # repeatable flags: sweep param.NAME, not the list


@dataclass(frozen=True)
class Range:
    """``KEY=lo:hi`` of ``--random``: uniform in [lo, hi] (integers for integer options)."""

    key: str
    low: float
    high: float


@dataclass(frozen=True)
class Trial:
    """One point of the sweep: its file name stem and its swept values (key -> typed value)."""

    name: str
    params: dict[str, Any]


class Space:
    """The sweepable keys of one run parser, and conversion of their values."""

    def __init__(self, run_parser: argparse.ArgumentParser) -> None:
        self.actions = {a.dest: a for a in run_parser._actions
                        if a.dest not in UNSWEEPABLE and a.option_strings}

    def canonical(self, key: str, flag: str) -> str:
        """``prediction-every`` -> ``prediction_every``; ``param.gain`` stays; unknown refused."""
        key = key.strip().removeprefix("--")
        if key.startswith(PARAM_PREFIX):
            if not key[len(PARAM_PREFIX):].isidentifier():
                raise UsageError(f"{flag}: {key!r} is not param.NAME with NAME a name")
            return key
        dest = key.replace("-", "_")
        if dest not in self.actions:
            known = ", ".join(sorted(d.replace("_", "-") for d in self.actions))
            raise UsageError(f"{flag}: unknown key {key!r} (a run option: {known}; or "
                             "param.NAME)")
        return dest

    def convert(self, key: str, text: str, flag: str) -> Any:
        """The typed value of ``text`` for ``key`` (checked as the run option checks it)."""
        if key.startswith(PARAM_PREFIX):
            return parse_value(text)
        action = self.actions[key]
        if action.nargs == 0:  # store_true
            lowered = text.strip().lower()
            if lowered not in ("true", "false"):
                raise UsageError(f"{flag}: {key} takes true or false, got {text!r}")
            return lowered == "true"
        try:
            value = action.type(text) if callable(action.type) else text
        except (argparse.ArgumentTypeError, ValueError) as exc:
            raise UsageError(f"{flag}: {key}={text}: {exc}") from None
        if action.choices is not None and value not in action.choices:
            raise UsageError(f"{flag}: {key}={text}: expected one of "
                             f"{', '.join(map(str, action.choices))}")
        return value

    def is_integer(self, key: str) -> bool:
        action = self.actions.get(key)
        return action is not None and action.type is not None and "int" in getattr(
            action.type, "__name__", "")

    def grid_entry(self, text: str, flag: str = "--grid") -> tuple[str, list[Any]]:
        """``KEY=v1,v2,...`` -> (key, typed values); ``KEY=v1;v2`` when values hold commas."""
        key, sep, values = text.partition("=")
        if not sep or not values.strip():
            raise UsageError(f"{flag} {text!r}: expected KEY=v1,v2,...")
        key = self.canonical(key, f"{flag} {text!r}")
        return key, [self.convert(key, v.strip(), f"{flag} {text!r}")
                     for v in values.split(";" if ";" in values else ",")]

    def range_entry(self, text: str, flag: str = "--random") -> Range:
        """``KEY=lo:hi`` -> a :class:`Range` of numbers the option accepts."""
        key, sep, bounds = text.partition("=")
        low_text, colon, high_text = bounds.partition(":")
        if not sep or not colon:
            raise UsageError(f"{flag} {text!r}: expected KEY=lo:hi")
        key = self.canonical(key, f"{flag} {text!r}")
        low = self.convert(key, low_text.strip(), f"{flag} {text!r}")
        high = self.convert(key, high_text.strip(), f"{flag} {text!r}")
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (low, high)):
            raise UsageError(f"{flag} {text!r}: lo and hi must be numbers")
        if not low <= high:
            raise UsageError(f"{flag} {text!r}: lo must not exceed hi")
        return Range(key, low, high)

    def sample(self, ranges: Sequence[Range], count: int, seed: int) -> list[dict[str, Any]]:
        """``count`` seeded points, each key uniform in its range (6 significant digits, so a
        trial's name holds its exact values)."""
        rng = random.Random(seed)
        points = []
        for _ in range(count):
            point: dict[str, Any] = {}
            for r in ranges:
                if self.is_integer(r.key) or (isinstance(r.low, int) and isinstance(r.high, int)):
                    point[r.key] = rng.randint(int(r.low), int(r.high))
                else:
                    point[r.key] = float(f"{rng.uniform(r.low, r.high):.6g}")
            points.append(point)
        return points


def expand(grid: Mapping[str, Sequence[Any]],
           samples: Sequence[Mapping[str, Any]] = ()) -> list[Trial]:
    """The Cartesian product of the grid, times every random sample (if any)."""
    keys = list(grid)
    points = [dict(zip(keys, values, strict=True))
              for values in itertools.product(*(grid[k] for k in keys))]
    if samples:
        points = [{**point, **sample} for point in points for sample in samples]
    return named(points)


def named(points: Iterable[dict[str, Any]]) -> list[Trial]:
    """Trials named ``key-value_key-value`` (file-safe); a clash gets ``-2``, ``-3``..."""
    trials, seen = [], set()
    for point in points:
        stem = trial_name(point)
        name, n = stem, 1
        while name in seen:
            n += 1
            name = f"{stem}-{n}"
        seen.add(name)
        trials.append(Trial(name, point))
    return trials


def trial_name(params: Mapping[str, Any]) -> str:
    if not params:
        return "trial"
    parts = [f"{key.removeprefix(PARAM_PREFIX)}-{format_value(value)}"
             for key, value in params.items()]
    return re.sub(r"[^A-Za-z0-9.+=-]+", "_", "_".join(parts))[:200]


def format_value(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    return str(value).lower() if isinstance(value, bool) else str(value)
