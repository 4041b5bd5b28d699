"""The machining sequence as the bridge plays it on the M1/M2 relays.

* :class:`SequenceSchedule` - exact nanosecond lookups on the table of
  :class:`hil.controllers.bench.problem.MachiningSequence`.
* :class:`SequencePlayer` - drives the relays from the table through the safety layer.
* :class:`SequenceOrigin` - the clock time of the sequence's start, which every ``t_s``
  counts from.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from hil.contracts import TimeSource
from hil.controllers.bench.problem import MachiningSequence, Stage
from hil.core.loop import Task

if TYPE_CHECKING:
    from hil.drivers.bench.safe_bench import SafeBench


class SequenceSchedule:
    """The machining sequence as the player plays it: exact lookups in integer nanoseconds
    on the stages of a :class:`~hil.controllers.bench.problem.MachiningSequence`."""

    def __init__(self, sequence: MachiningSequence) -> None:
        self.period_s = sequence.period_s
        self.stages = list(sequence.stages)
        self.relays = list(sequence.relays)
        self._period_ns = round(self.period_s * 1e9)
        self._starts_ns = [round(s.start_s * 1e9) for s in self.stages]

    def stage_at(self, t_ns: int) -> Stage:
        """The stage at ``t_ns`` after the sequence started (periodic)."""
        phase = t_ns % self._period_ns
        index = int(np.searchsorted(self._starts_ns, phase, side="right")) - 1
        return self.stages[index]

    def states_at(self, t_ns: int) -> dict[str, bool]:
        stage = self.stage_at(t_ns)
        return {name: name in stage.on for name in self.relays}

    def profile(self, dt_s: float) -> dict[str, np.ndarray]:
        """One period sampled every ``dt_s``: ``{relay: 0/1 array}`` (e.g. for predictions)."""
        n = round(self.period_s / dt_s)
        states = [self.states_at(round(k * dt_s * 1e9)) for k in range(n)]
        return {name: np.array([s[name] for s in states], dtype=np.int8)
                for name in self.relays}

class SequencePlayer(Task):
    """Plays the machining sequence on its relays from the first tick on (``t0_ns``)."""

    def __init__(self, bench: SafeBench, sequence: SequenceSchedule, *, divisor: int = 1,
                 name: str = "sequence") -> None:
        super().__init__(name, divisor)
        self.bench, self.sequence = bench, sequence
        self.t0_ns: int | None = None
        self._changes: dict[str, bool] = {}

    def compute(self, t_ns: int) -> None:
        """The relays whose state in the table differs from what is commanded."""
        if self.t0_ns is None:
            self.t0_ns = t_ns
        states = self.sequence.states_at(t_ns - self.t0_ns)
        commanded = self.bench.commanded()
        self._changes = {name: on for name, on in states.items() if commanded[name] != on}

    def write(self, t_ns: int) -> None:
        if self._changes and self.bench.link_up:
            self.bench.set_relays(self._changes, t_ns)


class SequenceOrigin:
    """Clock time of the machining sequence's start, which every ``t_s`` counts from: the
    player's first tick (the clock's time until then)."""

    def __init__(self, clock: TimeSource) -> None:
        self.clock = clock
        self.player: SequencePlayer | None = None

    def __call__(self) -> int:
        t0 = self.player.t0_ns if self.player is not None else None
        return t0 if t0 is not None else self.clock.time_ns()
