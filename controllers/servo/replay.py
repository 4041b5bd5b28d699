"""A controller that plays back recorded currents, one a tick, whatever the axis does: what a
twin is given to answer "does it respond as the machine did to the same commands?"."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


class CurrentReplay:
    """The ``k``-th call of :meth:`step` returns the ``k``-th current [mA]; after the last
    one, 0 mA."""

    def __init__(self, currents_ma: ArrayLike) -> None:
        self.currents_ma = np.asarray(currents_ma, dtype=float)
        self.tick = 0

    def step(self, position_deg: float, t_s: float) -> float:
        k, self.tick = self.tick, self.tick + 1
        return float(self.currents_ma[k]) if k < self.currents_ma.size else 0.0
