"""The servo run's safety limits, on by default (drive.toml ``[safety]``), in the spirit of a
drive's following-error window (CiA 402 0x6065/0x6066) and LinuxCNC's FERROR: whatever the
controller does, a runaway axis is stopped.

Checked every tick (the record phase), each one stops the run at the next tick boundary, the
drive quick-stopped and disabled, the limit named in a ``safety.stop`` event and in the
error the run ends with:

* following error: ``|position - reference|`` beyond ``following_error_deg`` for longer than
  ``following_error_ms``, both multi-turn (the reference placed where the axis started), so a
  window of any size holds, half a turn or more too;
* position outside ``[position_min_deg, position_max_deg]`` (multi-turn);
* ``|velocity|`` above ``velocity_max_deg_s``;
* more than ``stale_share_max`` of the cycles of the last ``stale_window_ms`` without fresh
  feedback (the controller is driving blind).

The defaults leave the built-in controllers every scenario of the papers (the largest
following error of a built-in is ~24 deg, in the disturbance scenario of Fig. 16; the fastest
motion 363 deg/s, the trapezoid) and stop a runaway within ``following_error_ms`` plus one
tick of the breach.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class ServoSafety:
    """The limits of ``[safety]`` (``enabled = false`` switches every one off)."""

    enabled: bool = True
    following_error_deg: float = 45.0
    following_error_ms: float = 10.0
    position_min_deg: float = -3600.0
    position_max_deg: float = 3600.0
    velocity_max_deg_s: float = 1800.0
    stale_share_max: float = 0.5
    stale_window_ms: float = 200.0


class SafetyMonitor:
    """The limits checked tick by tick; :meth:`check` names the first one crossed, once."""

    def __init__(self, limits: ServoSafety, period_s: float) -> None:
        self.limits = limits
        self._window_ticks = max(1, round(limits.following_error_ms / 1000 / period_s))
        self._stale_ticks = max(1, round(limits.stale_window_ms / 1000 / period_s))
        self._beyond = 0                     # ticks in a row beyond the following-error window
        self._stale: deque[bool] = deque(maxlen=self._stale_ticks)
        self._stale_count = 0
        self.stopped: str | None = None      # what stopped the run

    def check(self, t_s: float, error_deg: float, position_deg: float, velocity_deg_s: float,
              fresh: bool) -> str | None:
        """The limit this tick crosses, as one line (None: all hold, or already stopped)."""
        limits = self.limits
        if not limits.enabled or self.stopped is not None:
            return None
        found = None
        if abs(error_deg) > limits.following_error_deg:
            self._beyond += 1
            if self._beyond > self._window_ticks:
                found = (f"following error {abs(error_deg):.2f} deg beyond "
                         f"{limits.following_error_deg:g} deg for more than "
                         f"{limits.following_error_ms:g} ms")
        else:
            self._beyond = 0
        if found is None and not (limits.position_min_deg <= position_deg
                                  <= limits.position_max_deg):
            found = (f"position {position_deg:.2f} deg outside [{limits.position_min_deg:g}, "
                     f"{limits.position_max_deg:g}] deg")
        if found is None and abs(velocity_deg_s) > limits.velocity_max_deg_s:
            found = (f"velocity {abs(velocity_deg_s):.1f} deg/s above "
                     f"{limits.velocity_max_deg_s:g} deg/s")
        if found is None and not math.isfinite(position_deg + velocity_deg_s):
            found = f"non-finite feedback (position {position_deg}, velocity {velocity_deg_s})"
        if len(self._stale) == self._stale.maxlen and self._stale[0]:
            self._stale_count -= 1
        self._stale.append(not fresh)
        self._stale_count += not fresh
        if found is None and len(self._stale) == self._stale.maxlen and \
                self._stale_count > limits.stale_share_max * self._stale_ticks:
            found = (f"{self._stale_count} of the last {self._stale_ticks} cycles without fresh "
                     f"feedback (more than {limits.stale_share_max:.0%} in "
                     f"{limits.stale_window_ms:g} ms)")
        if found is not None:
            self.stopped = f"safety stop at t={t_s:.4f} s: {found}"
        return self.stopped
