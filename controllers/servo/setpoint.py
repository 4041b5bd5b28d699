"""The reference itself as the set point, for a drive that closes its own loop (CSP, CSV, PV):
the built-in ``setpoint`` controller.

The task steps a controller with the feedback of tick k and its set point is applied from that
SYNC on, so the feedback of tick k+1 shows what it did: the follower sends where the reference
is one period ahead, r((k+1) T) (a position), or the velocity that takes the axis there from
r(k T), (r((k+1) T) - r(k T)) / T (CSV, PV). It reads nothing of the position it is given:
the drive's loop does the following, and the run measures how well.
"""

from __future__ import annotations

from hil.controllers.base import POSITION, UNWRAPPED, VELOCITY
from hil.controllers.errors import ControllerSetupError
from hil.controllers.servo.references import Reference, ReferenceSamples


class SetPointFollower:
    """Sends ``reference`` as a position (``output`` ``"position"``) or as its derivative
    (``"velocity"``), stepped every ``period_s``."""

    position_input = UNWRAPPED  # the reference's own frame, turns included

    def __init__(self, reference: Reference, output: str, period_s: float) -> None:
        if output not in (POSITION, VELOCITY):
            raise ControllerSetupError(f"controller 'setpoint' sends the reference as a "
                                       f"{POSITION!r} or a {VELOCITY!r}: a drive that takes a "
                                       f"{output!r} needs a controller of its own")
        self.output = output
        self.period_s = period_s
        self.samples = ReferenceSamples(reference, period_s)

    def step(self, position_deg: float, t_s: float) -> float:
        k = round(t_s / self.period_s)
        ahead = self.samples(k + 1)
        if self.output == POSITION:
            return ahead
        return (ahead - self.samples(k)) / self.period_s
