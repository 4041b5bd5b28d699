"""Tolerances of a comparison, one per KPI or signal: ``exact``, ``abs:V``, ``rel:P%`` or
``tube:V,LAG`` (a band of V around the baseline, which the candidate may lead or lag by up to
LAG, ``2ms`` or ``0.002s``, as Simulink Test's time tolerance); or one-sided, for "did it get
worse?": ``max:V`` (at most V above the baseline, any amount below), ``min:V`` (at most V
below), ``worse:V`` (V the worse way of a KPI whose better direction is known:
:mod:`hil.compare.direction`), each V also as a percentage of the baseline (``worse:5%``).

Given as ``NAME=SPEC`` (``--tolerance rms_error_deg=rel:2%``), in a TOML file whose keys are
the names (``"/drive/feedback:position_deg" = "tube:0.01,2ms"``) or as the ``hil_baseline``
fixture's ``tolerances={NAME: SPEC}``; the name ``*`` sets the tolerance of everything no
other entry names. A message about one entry spells it as its front end does (a
:data:`Spelling`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, replace

from hil.compare.direction import LOWER, LOWER_IS_BETTER_WORDS, better
from hil.core.config import load_toml
from hil.core.verdict import unit_of
from hil.errors import ConfigError, UsageError

DEFAULT = "*"
_LAG = re.compile(r"^\s*([0-9.eE+-]+)\s*(ms|s)\s*$")
#: the sides of a tolerance: both ways of the baseline, or one (``worse``: the KPI's worse way)
BOTH, MAX, MIN, WORSE = "both", "max", "min", "worse"
ONE_SIDED = (MAX, MIN, WORSE)

#: how a front end writes one tolerance, ``(NAME, SPEC) -> text``, for its messages
Spelling = Callable[[str, str], str]


def flag_spelling(name: str, spec: str) -> str:
    """``--tolerance 'NAME=SPEC'`` (``hil compare``)."""
    return f"--tolerance '{name}={spec}'"


def fixture_spelling(name: str, spec: str) -> str:
    """``tolerances={"NAME": "SPEC"}`` (the ``hil_baseline`` fixture)."""
    return f'tolerances={{"{name}": "{spec}"}}'


@dataclass(frozen=True)
class Tolerance:
    """How far a candidate may stray: ``kind`` exact|abs|rel|tube; ``value`` the band (rel: a
    fraction of the baseline's magnitude); ``lag_s`` the time shift a tube allows; ``side``
    both, max (only above the baseline is bounded), min (only below) or worse (max or min by
    the KPI's better direction: :meth:`for_kpi`); ``better`` that direction once resolved."""

    kind: str
    value: float = 0.0
    lag_s: float = 0.0
    side: str = BOTH
    better: str = ""

    def text(self, name: str = "") -> str:
        """``exact``, ``abs 0.05``, ``rel 2%``, ``tube 0.01 deg +-2 ms``, ``max +5%``,
        ``min -0.05 deg``, ``max +5% (lower is better)`` from worse: (the JSON's form)."""
        unit = unit_of(name.rpartition(":")[2] or name)
        if self.kind == "exact":
            return "exact"
        band = f"{self.value * 100:g}%" if self.kind == "rel" else \
            f"{self.value:g}" + (f" {unit}" if unit else "")
        if self.side in (MAX, MIN):
            why = f" ({self.better} is better)" if self.better else ""
            return f"{self.side} {'+' if self.side == MAX else '-'}{band}{why}"
        if self.side == WORSE:
            return f"worse {band}"
        if self.kind == "tube":
            return f"tube {band} +-{self.lag_s * 1000:g} ms"
        return f"{self.kind} {band}"

    def spec(self) -> str:
        """The tolerance as it is written: ``rel:2%``, ``worse:5%``, ``tube:0.01,2ms``."""
        if self.kind == "exact":
            return "exact"
        band = f"{self.value * 100:g}%" if self.kind == "rel" else f"{self.value:g}"
        if self.kind == "tube":
            return f"tube:{band},{self.lag_s * 1000:g}ms"
        return f"{self.side if self.side != BOTH else self.kind}:{band}"

    def allowed(self, baseline: float) -> float:
        """The largest difference allowed around a baseline value (before any time shift)."""
        if self.kind == "rel":
            return self.value * abs(baseline)
        return 0.0 if self.kind == "exact" else self.value

    def holds(self, difference: float, allowed: float) -> bool:
        """candidate - baseline within ``allowed`` on the sides this tolerance bounds."""
        if self.side == MAX:
            return difference <= allowed
        if self.side == MIN:
            return -difference <= allowed
        return abs(difference) <= allowed

    def for_kpi(self, name: str, named: bool, spelling: Spelling) -> Tolerance:
        """``worse:`` made max or min by the KPI's better direction; on a KPI without one, a
        UsageError when the tolerance names it, two-sided when it comes from ``*``."""
        if self.side != WORSE:
            return self
        direction = better(name)
        if direction is not None:
            return replace(self, side=MAX if direction == LOWER else MIN, better=direction)
        if not named:
            return replace(self, side=BOTH)
        raise UsageError(f"{spelling(name, self.spec())}: {name} has no better direction "
                         f"(worse: knows errors, {', '.join(LOWER_IS_BETTER_WORDS[1:])}, "
                         "faults and costs: lower is better; realtime_factor: higher is "
                         "better); bound it with max:V or min:V")


EXACT = Tolerance("exact")


def parse_tolerance(spec: str, where: str = "--tolerance") -> Tolerance:
    """``exact``, ``abs:0.05``, ``rel:2%``, ``tube:0.01,2ms``, ``max:0.05``, ``worse:5%``
    -> Tolerance; else a UsageError ``WHERE 'SPEC': the problem``."""
    try:
        return _spec(spec)
    except ValueError as exc:
        raise UsageError(f"{where} {spec!r}: {exc}") from None


def parse_named(name: str, spec: str, spelling: Spelling) -> Tolerance:
    """The tolerance ``spec`` of ``name``; else a UsageError ``SPELLING: the problem``."""
    try:
        return _spec(spec)
    except ValueError as exc:
        raise UsageError(f"{spelling(name, spec)}: {exc}") from None


def _spec(spec: str) -> Tolerance:
    kind, _, rest = spec.strip().partition(":")
    if kind == "exact" and not rest:
        return EXACT
    if kind == "abs":
        return Tolerance("abs", _band(rest))
    if kind == "rel":
        if not rest.endswith("%"):
            raise ValueError("a relative tolerance is in percent, e.g. rel:2%")
        return Tolerance("rel", _band(rest[:-1]) / 100)
    if kind == "tube":
        band, _, lag = rest.partition(",")
        match = _LAG.match(lag)
        if not match:
            raise ValueError("a tube's lag needs its unit, ms or s, e.g. tube:0.01,2ms")
        lag_s = float(match.group(1)) * (1e-3 if match.group(2) == "ms" else 1.0)
        if not (math.isfinite(lag_s) and lag_s >= 0):
            raise ValueError("a tube's lag must be finite and >= 0")
        return Tolerance("tube", _band(band), lag_s)
    if kind in ONE_SIDED:
        if rest.endswith("%"):
            return Tolerance("rel", _band(rest[:-1]) / 100, side=kind)
        return Tolerance("abs", _band(rest), side=kind)
    raise ValueError("expected exact, abs:V, rel:P%, tube:V,LAG (LAG in ms or s, e.g. "
                     "tube:0.01,2ms) or one-sided max:V, min:V, worse:V (V or P%)")


def _band(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value >= 0):
        raise ValueError("the band must be a finite number >= 0")
    return value


def parse_entry(text: str) -> tuple[str, Tolerance]:
    """``NAME=SPEC`` of ``--tolerance`` -> (name, Tolerance)."""
    name, sep, spec = text.partition("=")
    if not sep or not name.strip():
        raise UsageError(f"--tolerance {text!r}: expected NAME=SPEC, e.g. "
                         "rms_error_deg=rel:2% or /drive/feedback:position_deg=abs:0.01")
    return name.strip(), parse_named(name.strip(), spec, flag_spelling)


def tolerances_file(path: str) -> dict[str, Tolerance]:
    """A tolerances TOML file: ``NAME = "SPEC"`` lines (``"*"`` for the default)."""
    data, _ = load_toml(path)
    out = {}
    for name, spec in data.items():
        if not isinstance(spec, str):
            raise ConfigError(f"{path}: key {name!r} must be a string such as \"rel:2%\", "
                              f"not {type(spec).__name__}")
        try:
            out[name] = _spec(spec)
        except ValueError as exc:
            raise ConfigError(f"{path}: key {name!r} = {spec!r}: {exc}") from None
    return out

