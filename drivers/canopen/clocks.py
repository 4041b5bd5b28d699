"""The time a master goes by (:class:`~hil.drivers.canopen.state.MasterClock`): its watchdogs,
heartbeats and state waits.

* :class:`MonotonicClock` - the wall clock, for a drive that keeps its own (real hardware, a
  real-time run);
* :class:`SyncClock` - lockstep over a bus with a drive that keeps the master's time: time is
  the SYNCs this master has put on the bus, one communication cycle each, and waiting sends
  SYNCs; so a pause on either side (a busy machine, a debugger) is no time at all;
* :class:`ClockSwitch` - the one a master holds, so the rig can hand it the drive's kind of
  time once it knows (before anything is waited for).
"""

from __future__ import annotations

import math
import time

from hil.drivers.canopen.link import Link
from hil.drivers.canopen.state import MasterClock
from hil.protocols.cia301 import SYNC_COB_ID


class MonotonicClock:
    """The master's time on real hardware: the monotonic clock, and a real sleep."""

    @staticmethod
    def time_ns() -> int:
        return time.monotonic_ns()

    @staticmethod
    def sleep(seconds: float) -> None:
        time.sleep(seconds)


class SyncClock:
    """Lockstep time on a bus: the SYNCs ``link`` has sent, ``period_s`` each; :meth:`sleep`
    lets time pass by sending SYNCs (a drive on SYNC time steps its axis and its timers)."""

    def __init__(self, link: Link, period_s: float) -> None:
        self.link = link
        self.period_ns = round(period_s * 1e9)
        self._origin = link.syncs_sent

    def time_ns(self) -> int:
        return (self.link.syncs_sent - self._origin) * self.period_ns

    def sleep(self, seconds: float) -> None:
        for _ in range(max(1, math.ceil(seconds * 1e9 / self.period_ns))):
            self.link.send([(SYNC_COB_ID, b"")])


class ClockSwitch:
    """A :class:`MasterClock` whose clock can be swapped (:attr:`clock`): the master and its
    services hold this one."""

    def __init__(self, clock: MasterClock) -> None:
        self.clock = clock

    def time_ns(self) -> int:
        return self.clock.time_ns()

    def sleep(self, seconds: float) -> None:
        self.clock.sleep(seconds)
