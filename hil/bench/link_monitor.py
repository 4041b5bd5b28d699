"""The bench link's monitor: the intervals the link was lost, and the run's end when it
stays lost, its emulator is gone or another master drives the bench.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from hil.core.loop import Task

if TYPE_CHECKING:
    from hil.core.session import Session
    from hil.drivers.bench.safe_bench import SafeBench


class LinkMonitor(Task):
    """Every sample: the intervals the bench link was declared lost (``down``, clock ns) and
    the run's end when it stays lost ``give_up_s`` (event ``link.gave_up``, loop stopped with
    reason ``link lost``; the relays go to their safe level as at every stop), at once when
    ``peer_gone`` says the emulator the run is in lockstep with is gone (the link lost and
    given up on in the same sample), or as soon as a relay is found switched by someone else
    (``foreign``: event ``bench.foreign_master``)."""

    def __init__(self, bench: SafeBench, session: Session, give_up_s: float, divisor: int = 1,
                 name: str = "link", peer_gone: Callable[[], str | None] = lambda: None
                 ) -> None:
        super().__init__(name, divisor)
        self.bench, self.session = bench, session
        self.peer_gone = peer_gone
        self.give_up_ns = round(give_up_s * 1e9)
        self.down: list[list[int | None]] = []  # [lost at, restored at or None]
        self.gave_up = False
        self.foreign: str | None = None  # another master seen on the bench: the run stops

    def read(self, t_ns: int) -> None:
        if self.bench.stats.foreign_changes and self.foreign is None:
            self.foreign = ("a relay switched with no write of this run: another master is "
                            f"driving the bench at {self.bench.url}; the run stopped")
            self.session.event("bench.foreign_master", self.foreign, level="error",
                               source="bench")
            self.session.loop.stop("another master on the bench")
        gone = self.peer_gone()
        if gone is not None and not self.gave_up:
            self.bench.lose_link(gone)
        up = self.bench.link_up
        if not up and (not self.down or self.down[-1][1] is not None):
            self.down.append([t_ns, None])
        elif up and self.down and self.down[-1][1] is None:
            self.down[-1][1] = t_ns
        if self.gave_up:
            return
        if gone is not None:
            self._give_up(f"bench link lost: the bench emulator is gone ({gone}): the run stops",
                          f"link lost: the bench emulator is gone ({gone})")
            return
        if up or not self.give_up_ns:
            return
        lost_at = self.down[-1][0]
        assert lost_at is not None
        if t_ns - lost_at >= self.give_up_ns:
            seconds = self.give_up_ns / 1e9
            self._give_up(f"bench link lost for {seconds:g} s (bus.give_up_s): the run stops",
                          f"link lost for {seconds:g} s")

    def _give_up(self, message: str, reason: str) -> None:
        self.gave_up = True
        self.session.event("link.gave_up", message, level="error", source="bench")
        self.session.loop.stop(reason)

    def intervals(self, end_ns: int) -> list[tuple[int, int]]:
        """The lost intervals, an open one closed at ``end_ns``."""
        return [(a, b if b is not None else end_ns) for a, b in self.down if a is not None]
