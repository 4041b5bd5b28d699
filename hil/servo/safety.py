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
  feedback (the controller is driving blind). The message names the side that was late
  (:func:`judge_stale`): the drive, whose replies were not back when the loop read them, or
  the loop, which did not keep its schedule for those ticks; with the figures of both.

The defaults leave the built-in controllers every scenario of the papers (the largest
following error of a built-in is ~24 deg, in the disturbance scenario of Fig. 16; the fastest
motion 363 deg/s, the trapezoid) and stop a runaway within ``following_error_ms`` plus one
tick of the breach.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

#: a tick of the loop was late when it started more than this share of the period after its
#: slot (``hil doctor``'s 100 us lateness p99 at 2 kHz) or after skipped ticks
LOOP_ON_TIME_SHARE = 0.2
#: the loop is the late side when at least this share of the stale cycles had a late tick
#: (the one that sent its SYNC or the one that read it)
LOOP_STALE_SHARE = 0.5



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


#: the limits of ``[safety]`` that may change while a run runs, each only the stricter way:
#: name -> (unit, "lower" or "higher", what it is)
STRICTER: dict[str, tuple[str, str, str]] = {
    "following_error_deg": ("deg", "lower", "the following-error window"),
    "following_error_ms": ("ms", "lower", "how long the error may stay beyond the window"),
    "position_min_deg": ("deg", "higher", "the lowest position allowed (multi-turn)"),
    "position_max_deg": ("deg", "lower", "the highest position allowed (multi-turn)"),
    "velocity_max_deg_s": ("deg/s", "lower", "the highest speed allowed"),
    "stale_share_max": ("", "lower", "the share of cycles without fresh feedback allowed"),
}


@dataclass(frozen=True)
class StaleVerdict:
    """Which side was late over cycles without fresh feedback, and the figures of both.

    The master reads a cycle's replies no earlier than ``rx_timeout`` after its SYNC, so a
    stale cycle is a reply the drive did not have back in that time: the drive's, unless the
    tick that sent its SYNC or the one that read it was late (see :data:`LOOP_ON_TIME_SHARE`):
    its SYNC then left off the grid the drive expects it on, and the cycle is the loop's. The
    loop is named when at least :data:`LOOP_STALE_SHARE` of the stale cycles are its own: a
    drive silent for 200 cycles is the drive, whatever two or three late ticks among them."""

    stale: int                   # cycles without fresh feedback
    cycles: int                  # cycles looked at
    ticks: int                   # the ticks that sent the stale cycles' SYNC or read them
    late_ticks: int              # those of them that were late
    loop_stale: int              # stale cycles with a late tick (the loop's own)
    skipped: int                 # ticks the loop skipped just before them
    period_us: float
    loop_p99_us: float           # lateness of those ticks
    loop_max_us: float
    rtt_p99_us: float | None     # SYNC to both TPDOs read, of the fresh cycles (None: none)

    @property
    def side(self) -> str:
        """``drive`` or ``loop`` (the side that was late), ``none`` without stale cycles."""
        if not self.stale:
            return "none"
        return "loop" if self.loop_stale >= LOOP_STALE_SHARE * self.stale else "drive"

    def describe(self) -> str:
        """The verdict in one clause, e.g. ``the drive was late (...); the loop was on time
        (...)``."""
        replies = (f"{self.stale} replies not back when the loop read them"
                   + (f", the {self.cycles - self.stale} in time: SYNC to reply read p99 "
                      f"{self.rtt_p99_us:.0f} us" if self.rtt_p99_us is not None else ""))
        schedule = (f"{self.late_ticks} of the {self.ticks} ticks that sent or read them "
                    f"started over {LOOP_ON_TIME_SHARE * self.period_us:.0f} us late"
                    + (f" or after skipped ticks ({self.skipped})" if self.skipped else "")
                    + f", {self.loop_stale} stale cycles after a late tick"
                    + f", lateness p99 {self.loop_p99_us:.0f} us, max {self.loop_max_us:.0f} us")
        if self.side == "loop":
            return f"the loop was late ({schedule}); the drive: {replies}"
        if self.side == "drive":
            return f"the drive was late ({replies}); the loop was on time ({schedule})"
        return "no stale cycle"


def judge_stale(stale: npt.ArrayLike, late_us: npt.ArrayLike, rtt_us: npt.ArrayLike,
                period_s: float, ticks: npt.ArrayLike | None = None) -> StaleVerdict:
    """The :class:`StaleVerdict` of a run of cycles: per cycle whether it was stale, the
    loop's lateness of its tick [us], its ``rtt_us`` (fresh cycles) and its tick number
    (``ticks``; default: no tick skipped). A stale cycle's tick reads the reply and the tick
    run before it sent the SYNC: both count, late when they started more than
    :data:`LOOP_ON_TIME_SHARE` of the period after their slot or right after skipped ticks."""
    flags = np.asarray(stale, bool)
    late = np.asarray(late_us, float)
    rtt = np.asarray(rtt_us, float)[~flags]
    numbers = np.arange(flags.size) if ticks is None else np.asarray(ticks, np.int64)
    gaps = (np.diff(numbers, prepend=numbers[:1]) - 1).clip(min=0)
    stale_at = np.flatnonzero(flags)
    involved = np.union1d(stale_at, np.maximum(stale_at - 1, 0)).astype(np.int64)
    lateness, skipped = late[involved], gaps[involved]
    tick_late = (late > LOOP_ON_TIME_SHARE * period_s * 1e6) | (gaps > 0)
    late_ticks = tick_late[involved]
    loop_stale = tick_late[stale_at] | tick_late[np.maximum(stale_at - 1, 0)]
    return StaleVerdict(
        stale=int(stale_at.size), cycles=int(flags.size), ticks=int(involved.size),
        late_ticks=int(late_ticks.sum()), loop_stale=int(loop_stale.sum()),
        skipped=int(skipped.sum()),
        period_us=period_s * 1e6,
        loop_p99_us=float(np.percentile(lateness, 99)) if involved.size else 0.0,
        loop_max_us=float(lateness.max()) if involved.size else 0.0,
        rtt_p99_us=float(np.percentile(rtt, 99)) if rtt.size else None)


class SafetyMonitor:
    """The limits checked tick by tick; :meth:`check` names the first one crossed, once."""

    def __init__(self, limits: ServoSafety, period_s: float, axis: str | None = None) -> None:
        self.limits = limits
        self.period_s = period_s
        self._stop_prefix = f"axis {axis}: " if axis is not None else ""  # one of several
        self._window_ticks = max(1, round(limits.following_error_ms / 1000 / period_s))
        self._stale_ticks = max(1, round(limits.stale_window_ms / 1000 / period_s))
        self._beyond = 0                     # ticks in a row beyond the following-error window
        # the cycles of the stale window: (stale, loop lateness [us], rtt [us], tick number)
        self._cycles: deque[tuple[bool, float, float, int]] = deque(maxlen=self._stale_ticks)
        self._stale_count = 0
        self.stopped: str | None = None      # what stopped the run
        self.verdict: StaleVerdict | None = None  # who was late, when the stale share stopped it

    def check(self, t_s: float, error_deg: float, position_deg: float, velocity_deg_s: float,
              fresh: bool, rtt_us: float = 0.0, late_us: float = 0.0) -> str | None:
        """The limit this tick crosses, as one line (None: all hold, or already stopped).
        ``rtt_us``: the feedback's SYNC-to-reply time; ``late_us``: the loop's lateness of
        this tick (both for naming the late side of a stale-share stop)."""
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
        elif self._beyond:
            self._beyond = 0
        if found is None:  # the first limit crossed, in this order
            if not limits.position_min_deg <= position_deg <= limits.position_max_deg:
                found = (f"position {position_deg:.2f} deg outside "
                         f"[{limits.position_min_deg:g}, {limits.position_max_deg:g}] deg")
            elif abs(velocity_deg_s) > limits.velocity_max_deg_s:
                found = (f"velocity {abs(velocity_deg_s):.1f} deg/s above "
                         f"{limits.velocity_max_deg_s:g} deg/s")
            elif not math.isfinite(position_deg + velocity_deg_s):
                found = (f"non-finite feedback (position {position_deg}, velocity "
                         f"{velocity_deg_s})")
        cycles, window = self._cycles, self._stale_ticks  # the deque's maxlen
        if len(cycles) == window and cycles[0][0]:  # a stale cycle leaves the window
            self._stale_count -= 1
        cycles.append((not fresh, late_us, rtt_us, round(t_s / self.period_s)))
        if not fresh:
            self._stale_count += 1
        if found is None and self._stale_count > limits.stale_share_max * window and \
                len(cycles) == window:
            self.verdict = self._judge()
            found = (f"{self._stale_count} of the last {self._stale_ticks} cycles without fresh "
                     f"feedback (more than {limits.stale_share_max:.0%} in "
                     f"{limits.stale_window_ms:g} ms): {self.verdict.describe()}")
        if found is not None:
            self.stopped = f"{self._stop_prefix}safety stop at t={t_s:.4f} s: {found}"
        return self.stopped

    def tighten(self, name: str, value: float) -> None:
        """Make the limit ``name`` (a field of :class:`ServoSafety`) ``value`` from this tick
        on; the tuner lets it move only the stricter way (:data:`STRICTER`)."""
        changed: dict[str, Any] = {name: value}
        self.limits = replace(self.limits, **changed)
        self._window_ticks = max(1, round(self.limits.following_error_ms / 1000 / self.period_s))

    def _judge(self) -> StaleVerdict:
        stale, late, rtt, ticks = zip(*self._cycles, strict=True)
        return judge_stale(stale, late, rtt, self.period_s, ticks)
