"""Tolerances of a comparison, one per KPI or signal: ``exact``, ``abs:V``, ``rel:P%`` or
``tube:V,LAG`` (a band of V around the baseline, which the candidate may lead or lag by up to
LAG, ``2ms`` or ``0.002s``, as Simulink Test's time tolerance).

Given as ``NAME=SPEC`` (``--tolerance rms_error_deg=rel:2%``) or in a TOML file whose keys are
the names (``"/drive/feedback:position_deg" = "tube:0.01,2ms"``); the name ``*`` sets the
tolerance of everything no other entry names.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from hil.core.config import load_toml
from hil.core.verdict import unit_of
from hil.errors import ConfigError, UsageError

DEFAULT = "*"
_LAG = re.compile(r"^\s*([0-9.eE+-]+)\s*(ms|s)\s*$")


@dataclass(frozen=True)
class Tolerance:
    """How far a candidate may stray: ``kind`` exact|abs|rel|tube; ``value`` the band (rel: a
    fraction of the baseline's magnitude); ``lag_s`` the time shift a tube allows."""

    kind: str
    value: float = 0.0
    lag_s: float = 0.0

    def text(self, name: str = "") -> str:
        """``exact``, ``abs 0.05``, ``rel 2%``, ``tube 0.01 deg +-2 ms`` (the JSON's form)."""
        unit = unit_of(name.rpartition(":")[2] or name)
        if self.kind == "exact":
            return "exact"
        if self.kind == "rel":
            return f"rel {self.value * 100:g}%"
        band = f"{self.value:g}" + (f" {unit}" if unit else "")
        if self.kind == "abs":
            return f"abs {band}"
        return f"tube {band} +-{self.lag_s * 1000:g} ms"

    def allowed(self, baseline: float) -> float:
        """The largest difference allowed around a baseline value (before any time shift)."""
        if self.kind == "rel":
            return self.value * abs(baseline)
        return 0.0 if self.kind == "exact" else self.value


EXACT = Tolerance("exact")


def parse_tolerance(spec: str, where: str = "--tolerance") -> Tolerance:
    """``exact``, ``abs:0.05``, ``rel:2%``, ``tube:0.01,2ms`` -> Tolerance; else a
    UsageError ``WHERE 'SPEC': the problem``."""
    try:
        return _spec(spec)
    except ValueError as exc:
        raise UsageError(f"{where} {spec!r}: {exc}") from None


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
    raise ValueError("expected exact, abs:V, rel:P% or tube:V,LAG (LAG in ms or s, e.g. "
                     "tube:0.01,2ms)")


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
    try:
        return name.strip(), _spec(spec)
    except ValueError as exc:
        raise UsageError(f"--tolerance {text!r}: {exc}") from None


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

