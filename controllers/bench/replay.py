"""A bench controller that plays back recorded relay states, tick by tick, whatever the plant
does: what a twin is given to answer "does it draw the power the machine drew when its relays
switched the same way?"."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike

from hil.controllers.base import BenchObservation


class RelayReplay:
    """The relays' states to write at tick ``k`` (0/1 arrays, one entry a tick, every array
    as long); after the last tick, the last states held. :meth:`decide` is the tick of the
    observation's time (``t_s`` / ``period_s``), so a decision every tick replays every
    switch at the tick it was made."""

    def __init__(self, states: Mapping[str, ArrayLike], period_s: float) -> None:
        self.states = {name: np.asarray(values, dtype=bool) for name, values in states.items()}
        lengths = {values.size for values in self.states.values()}
        if len(lengths) != 1 or 0 in lengths:
            raise ValueError(f"expected relays' states of one length, at least 1, got {lengths}")
        self.ticks = lengths.pop()
        self.period_s = period_s

    def at(self, tick: int) -> dict[str, bool]:
        """The states written at ``tick`` (the last ones after the recording's end)."""
        k = min(max(tick, 0), self.ticks - 1)
        return {name: bool(values[k]) for name, values in self.states.items()}

    def decide(self, obs: BenchObservation) -> dict[str, bool]:
        return self.at(round(obs.t_s / self.period_s))
