"""Numbers with a unit, as a flag or a config key takes them: ``--duration`` and
``following_error_ms`` take a bare number of their unit. A value written with a unit
(``10ms``, ``0.3A``) is refused with the unit it takes and the value converted into it, by
:func:`unit_hint`; a bare number far below what the unit makes plausible (a current of 0.3 mA:
amperes, surely) by :func:`implausible`."""

from __future__ import annotations

import math
import re

#: unit -> (what it measures, its size in that quantity's base unit)
UNITS: dict[str, tuple[str, float]] = {
    "s": ("time", 1.0), "ms": ("time", 1e-3), "us": ("time", 1e-6), "µs": ("time", 1e-6),
    "min": ("time", 60.0), "h": ("time", 3600.0),
    "A": ("current", 1.0), "mA": ("current", 1e-3),
    "deg": ("angle", 1.0), "rad": ("angle", 180.0 / math.pi), "rev": ("angle", 360.0),
    "deg/s": ("speed", 1.0), "rpm": ("speed", 6.0), "deg/s^2": ("acceleration", 1.0),
    "Hz": ("frequency", 1.0), "kHz": ("frequency", 1e3),
    "bit/s": ("bitrate", 1.0), "kbit/s": ("bitrate", 1e3), "Mbit/s": ("bitrate", 1e6),
    "VA": ("power", 1.0), "kVA": ("power", 1e3),
}
_WITH_UNIT = re.compile(r"^\s*([-+]?[0-9.]+(?:[eE][-+]?[0-9]+)?)\s*([A-Za-zµ/]+)\s*$")
_UNIT_NAMES = {"s": "seconds", "mA": "mA", "deg": "degrees", "Hz": "Hz", "bit/s": "bit/s"}


def unit_name(unit: str) -> str:
    """How a message names ``unit`` (``s``: seconds)."""
    return _UNIT_NAMES.get(unit, unit)


def unit_hint(text: str, unit: str) -> str:
    """Why ``text`` is not a number of ``unit``, and what to write instead."""
    match = _WITH_UNIT.match(text)
    named = unit_name(unit)
    if match is None:
        return f"expected a number of {named}, got {text!r}"
    number, written = float(match.group(1)), match.group(2)
    known = UNITS.get(written) or next((v for k, v in UNITS.items()
                                        if k.lower() == written.lower()), None)
    if known is None or known[0] != UNITS[unit][0]:
        return f"expected a number of {named}, got {text!r} ({written!r} is not a unit of it)"
    converted = number * known[1] / UNITS[unit][1]
    return (f"takes a number of {named}, without its unit: {text!r} is {converted:g} "
            f"(write {converted:g})")


def written_with_unit(text: str) -> bool:
    """Whether ``text`` reads as a number followed by a unit (``'10ms'``, ``'0.3 A'``)."""
    return _WITH_UNIT.match(text) is not None


def implausible(value: float, unit: str, smallest_plausible: float, more_likely: str) -> str:
    """Why ``value`` [``unit``] below ``smallest_plausible`` is most likely a number of
    ``more_likely``: ``0.3 mA is below 1 mA: the value is in mA (0.3 A would be 300 mA)``."""
    scale = UNITS[more_likely][1] / UNITS[unit][1]
    return (f"{value:g} {unit} is below {smallest_plausible:g} {unit}: the value is in {unit} "
            f"({value:g} {more_likely} would be {value * scale:g} {unit})")
