"""The ranges the code can honour, for every value that reaches a loop, a horizon, an
allocation or a timestamp; a value outside is one line naming the flag or key (exit 2),
before anything is opened.

* :data:`MAX_DURATION_S` - a run's length: about 11.6 days, far inside MCAP's nanosecond
  timestamps (584 years) and the reach of a run's memory (constant per tick);
* a run shorter than one tick of its loop runs nothing: refused as well;
* :data:`MAX_DWELL_S` - a relay's minimum on/off time (the EEC plans over it in steps);
* :data:`MAX_EEC_HORIZON_S`, :data:`MAX_MPC_HORIZON` - the optimisers' horizons (the problem
  grows with them: past these a single decision would take minutes and gigabytes).
"""

from __future__ import annotations

import math

from hil.errors import UsageError

MAX_DURATION_S = 1e6
#: a current below 1 mA sends nothing (one torque unit is 1 mA at the default scaling) and
#: was most likely written in amperes: (the smallest plausible current [mA], the likely unit)
PLAUSIBLE_MILLIAMPS = (1.0, "A")
MAX_DWELL_S = 3600.0
MAX_EEC_HORIZON_S = 600
MAX_MPC_HORIZON = 1000


def check_duration(seconds: float, flag: str, tick_s: float) -> None:
    """``seconds`` of run: at least one tick of ``tick_s``, at most :data:`MAX_DURATION_S`."""
    if not (isinstance(seconds, (int, float)) and math.isfinite(seconds)):
        raise UsageError(f"{flag} must be a finite number of seconds, got {seconds!r}")
    if seconds < tick_s:
        raise UsageError(f"{flag} {seconds:g} s is shorter than one tick ({tick_s:g} s): "
                         "the run would do nothing")
    if seconds > MAX_DURATION_S:
        raise UsageError(f"{flag} {seconds:g} s is longer than a run can be "
                         f"({MAX_DURATION_S:g} s, about {MAX_DURATION_S / 86400:.1f} days)")


def check_at_most(value: float, limit: float, flag: str, why: str) -> None:
    """``value`` of ``flag`` no larger than ``limit`` (``why``: what the limit protects)."""
    if value > limit:
        raise UsageError(f"{flag} {value:g} is above {limit:g}: {why}")


def check_milliamps(value: float, flag: str) -> None:
    """A current limit in mA: finite and at least 1 mA (below it nothing is sent; a value
    below 1 is most likely amperes)."""
    if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value)
                                       and value > 0):
        raise UsageError(f"{flag} must be a positive finite current in mA, got {value!r}")
    if value < PLAUSIBLE_MILLIAMPS[0]:
        raise UsageError(f"{flag} {value:g} mA is below 1 mA: the current is in mA "
                         f"({value:g} A would be {flag} {value * 1000:g})")
