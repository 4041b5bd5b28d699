"""Flag values with a unit: ``--duration`` in s, ``--umax`` in mA. A value written in another
unit (``10ms``, ``0.3A``) is refused with the unit the flag takes and the value converted into
it; a bare number that is most likely another unit (``--umax 0.3``: amperes) likewise."""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable

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


def _unit_hint(text: str, unit: str) -> str:
    """Why ``text`` is not a number of ``unit``, and what to write instead."""
    match = _WITH_UNIT.match(text)
    named = _UNIT_NAMES.get(unit, unit)
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


def quantity(unit: str, *, above: float | None = 0.0, at_least: float | None = None,
             smallest_plausible: float | None = None,
             more_likely: str | None = None) -> Callable[[str], float]:
    """An argparse type: a finite number of ``unit`` (> ``above``, >= ``at_least``). A value
    below ``smallest_plausible`` is refused as most likely written in ``more_likely``."""

    def convert(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(_unit_hint(text, unit)) from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number of {unit}, got {text}")
        if above is not None and not value > above:
            raise argparse.ArgumentTypeError(f"expected a number of {unit} above {above:g}, "
                                             f"got {text}")
        if at_least is not None and value < at_least:
            raise argparse.ArgumentTypeError(f"expected a number of {unit} >= {at_least:g}, "
                                             f"got {text}")
        if smallest_plausible is not None and value < smallest_plausible and more_likely:
            scale = UNITS[more_likely][1] / UNITS[unit][1]
            raise argparse.ArgumentTypeError(
                f"{text} {unit} is below {smallest_plausible:g} {unit}: the value is in "
                f"{unit} ({text} {more_likely} would be {value * scale:g} {unit})")
        return value

    convert.__name__ = f"number of {unit}"  # argparse names the type in some errors
    return convert


#: the common ones
seconds = quantity("s")
seconds_or_zero = quantity("s", above=None, at_least=0.0)
milliamps = quantity("mA", smallest_plausible=1.0, more_likely="A")
degrees = quantity("deg", above=None)
degrees_per_s = quantity("deg/s")
degrees_per_s2 = quantity("deg/s^2")
