"""Flag values with a unit: ``--duration`` in s, ``--umax`` in mA. A value written in another
unit (``10ms``, ``0.3A``) is refused with the unit the flag takes and the value converted into
it; a bare number that is most likely another unit (``--umax 0.3``: amperes) likewise."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from hil.core.ranges import PLAUSIBLE_MILLIAMPS
from hil.core.units import implausible, unit_hint


def quantity(unit: str, *, above: float | None = 0.0, at_least: float | None = None,
             smallest_plausible: float | None = None,
             more_likely: str | None = None) -> Callable[[str], float]:
    """An argparse type: a finite number of ``unit`` (> ``above``, >= ``at_least``). A value
    below ``smallest_plausible`` is refused as most likely written in ``more_likely``."""

    def convert(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(unit_hint(text, unit)) from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number of {unit}, got {text}")
        if above is not None and not value > above:
            raise argparse.ArgumentTypeError(f"expected a number of {unit} above {above:g}, "
                                             f"got {text}")
        if at_least is not None and value < at_least:
            raise argparse.ArgumentTypeError(f"expected a number of {unit} >= {at_least:g}, "
                                             f"got {text}")
        if smallest_plausible is not None and value < smallest_plausible and more_likely:
            raise argparse.ArgumentTypeError(
                implausible(value, unit, smallest_plausible, more_likely))
        return value

    convert.__name__ = f"number of {unit}"  # argparse names the type in some errors
    return convert


#: the common ones
seconds = quantity("s")
seconds_or_zero = quantity("s", above=None, at_least=0.0)
milliamps = quantity("mA", smallest_plausible=PLAUSIBLE_MILLIAMPS[0],
                     more_likely=PLAUSIBLE_MILLIAMPS[1])
degrees = quantity("deg", above=None)
degrees_per_s = quantity("deg/s")
degrees_per_s2 = quantity("deg/s^2")
