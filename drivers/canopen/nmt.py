"""NMT and heartbeats (CiA 301 7.2.8): the master's commands to the node, the master's own
heartbeat (produced from the cyclic exchange, which is when the master is alive), and the
drive's heartbeat watched: its silence and its boot-up message."""

from __future__ import annotations

from collections.abc import Callable

from hil.drivers.canopen.link import Link
from hil.protocols.can_frames import Frame
from hil.protocols.cia301 import HEARTBEAT_BASE, NMT_BOOT_UP, NMT_COB_ID, NMT_OPERATIONAL


class Nmt:
    """NMT commands to one node, over ``link``."""

    def __init__(self, link: Link, node_id: int) -> None:
        self.link, self.node_id = link, node_id

    def command(self, command: int) -> None:
        """One NMT command (``hil.protocols.cia301.NMT_START``...) to this node."""
        self.link.send([(NMT_COB_ID, bytes([command, self.node_id]))])


class HeartbeatProducer:
    """The master's heartbeat (node id ``producer_id``, state OPERATIONAL) every
    ``period_ms`` (0: none), added to the cycle that is due."""

    def __init__(self, producer_id: int, period_ms: int, now_ns: Callable[[], int]) -> None:
        self.frame: Frame = (HEARTBEAT_BASE + producer_id, bytes([NMT_OPERATIONAL]))
        self.period_ns = period_ms * 1_000_000
        self._now_ns = now_ns
        self._next_ns: int | None = None

    def restart(self) -> None:
        """The next cycle sends one."""
        self._next_ns = None

    def due(self) -> bool:
        """Whether this cycle carries a heartbeat (then the next is one period later)."""
        if not self.period_ns:
            return False
        now = self._now_ns()
        if self._next_ns is None or now >= self._next_ns:
            self._next_ns = now + self.period_ns
            return True
        return False


class HeartbeatWatch:
    """The drive's heartbeat: when it was last heard, and a boot-up message (the drive
    restarted). Silent for three periods (CiA 301 consumers allow 1.5-3) is a lost link."""

    def __init__(self, node_id: int, period_ms: int, now_ns: Callable[[], int]) -> None:
        self.cob_id = HEARTBEAT_BASE + node_id
        self.period_ms = period_ms
        self.timeout_ns = 3 * period_ms * 1_000_000
        self._now_ns = now_ns
        self.last_ns = 0
        self.rebooted = False

    def restart(self) -> None:
        """Watched from now on."""
        self.last_ns = self._now_ns()
        self.rebooted = False

    def on_frame(self, data: bytes, watching: bool) -> bool:
        """A heartbeat of the drive; True when it is a boot-up while ``watching``."""
        if not data:
            return False
        self.last_ns = self._now_ns()
        if data[0] == NMT_BOOT_UP and watching:
            self.rebooted = True
            return True
        return False

    def silent_ns(self, now_ns: int | None = None) -> int | None:
        """How long the drive has been silent (at ``now_ns``, a time of the clock it was given;
        default: now), when that is longer than allowed; else None."""
        if not self.period_ms:
            return None
        silent = (self._now_ns() if now_ns is None else now_ns) - self.last_ns
        return silent if silent > self.timeout_ns else None
