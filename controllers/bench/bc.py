"""The basic controller (BC) of the energy paper: hysteresis on the resource levels.

Each peripheral P_j switches on when its level q_j reaches the bottom of its range and off when
it reaches the top, honouring the same minimum dwell as the EEC. The levels are read once per
decision step, so "reaches" means "would cross within the next step": on when
``q_j <= q_min + |alpha_j| * step`` (the largest drop in one step), off when
``q_j >= q_max - eta_j * step`` (the largest rise). BC knows neither the machining sequence
nor the power: it is the rule the EEC falls back to when its optimisation fails.

``band`` (0 < band <= 1, default 1: the paper's BC) narrows the hysteresis from the top: off at
``q_min + band (q_max - q_min)`` instead of ``q_max``, so the tank is kept lower and cycled
more often (the energy paper leaves BC's thresholds open; ``hil paper energy`` sweeps them).
"""

from __future__ import annotations

from collections.abc import Mapping

from hil.controllers.base import BenchObservation
from hil.controllers.bench.problem import BenchProblem, DwellClock
from hil.controllers.errors import ControllerSetupError


def hysteresis_rule(problem: BenchProblem, levels: Mapping[str, float],
                    dwell: DwellClock, t_s: float, step_s: float = 1.0,
                    band: float = 1.0) -> dict[str, bool]:
    """Relay states for the next step (peripherals only)."""
    out: dict[str, bool] = {}
    for res in problem.resources:
        name = res.supplier
        on = dwell.state[name]
        q = levels[res.name]
        top = res.q_max - (1.0 - band) * (res.q_max - res.q_min)  # q_max itself at band 1
        want = on
        if not on and q <= res.q_min + abs(res.alpha) * step_s:
            want = True
        elif on and q >= top - res.eta * step_s:
            want = False
        if want != on and not dwell.may_switch(name, t_s, problem.dwell_s[name]):
            want = on
        out[name] = want
    return out


class BasicController:
    """BC: :func:`hysteresis_rule` every step, with its own dwell bookkeeping (a
    :class:`~hil.controllers.base.BenchController`)."""

    def __init__(self, problem: BenchProblem, step_s: float = 1.0,
                 initial: Mapping[str, bool] | None = None, band: float = 1.0) -> None:
        if not 0.0 < band <= 1.0:
            raise ControllerSetupError(f"BC's band must be in (0, 1] (a fraction of each "
                                       f"level's operating range), got {band:g}")
        self.problem = problem
        self.step_s = step_s
        self.band = band
        self.dwell = DwellClock.start(problem.peripherals, initial)

    def decide(self, obs: BenchObservation) -> dict[str, bool]:
        """Observe the measured relay states and levels at ``obs.t_s``; return the command."""
        t_s = obs.t_s
        for name in self.problem.peripherals:
            self.dwell.update(name, bool(obs.relays.get(name, self.dwell.state[name])), t_s)
        command = hysteresis_rule(self.problem, obs.levels, self.dwell, t_s, self.step_s,
                                  self.band)
        for name, on in command.items():
            self.dwell.update(name, on, t_s)
        return command
