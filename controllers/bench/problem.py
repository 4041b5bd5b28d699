"""What the bench's controllers know about the machine (energy paper, sections II and IV).

* the machining sequence Lambda_M (Assumption 1: known a priori): a periodic table of stages,
  each naming the machining relays that are on;
* the peripherals P_j and their resources q_j (eq. 10, Table I): q_j(k+1) = q_j(k) +
  alpha_j [consumer on] + eta_j u_Pj(k) per second, with operating bounds;
* the minimum on/off dwell of every peripheral relay.

Pure data, no I/O: :mod:`hil.bench.config` builds them from the bench config (``[sequence]``,
``[plant.resources]``, ``[relays]``). The resource table sits under ``[plant]`` because the
emulator integrates the same relation; on a real bench it is the process knowledge of Table I.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Stage:
    """One stage of the machining sequence: ``[start_s, end_s)`` with relays ``on``."""

    start_s: float
    end_s: float
    on: frozenset[str]


@dataclass(frozen=True)
class MachiningSequence:
    """The periodic machining sequence Lambda_M (period ``period_s``)."""

    period_s: float
    stages: tuple[Stage, ...]
    relays: tuple[str, ...]  # machining relays, in a fixed order

    def stage_at(self, t_s: float) -> Stage:
        phase = t_s % self.period_s
        for stage in self.stages:
            if stage.start_s <= phase < stage.end_s:
                return stage
        return self.stages[-1]  # phase == period within round-off

    def relays_at(self, t_s: float) -> dict[str, bool]:
        on = self.stage_at(t_s).on
        return {name: name in on for name in self.relays}

    def on_fraction(self, relay: str, t0_s: float, t1_s: float) -> float:
        """Fraction of ``[t0_s, t1_s)`` during which ``relay`` is on (exact, stage by stage)."""
        if t1_s <= t0_s:
            return 0.0
        total = 0.0
        first_cycle = math.floor(t0_s / self.period_s)
        last_cycle = math.floor(t1_s / self.period_s)
        for cycle in range(first_cycle, last_cycle + 1):
            base = cycle * self.period_s
            for stage in self.stages:
                if relay not in stage.on:
                    continue
                lo = max(t0_s, base + stage.start_s)
                hi = min(t1_s, base + stage.end_s)
                total += max(0.0, hi - lo)
        return total / (t1_s - t0_s)

    def samples(self, t0_s: float, n: int, dt_s: float) -> np.ndarray:
        """Relay states (n x relays, 0/1) at ``t0_s + k dt_s``, k = 0..n-1."""
        out = np.zeros((n, len(self.relays)))
        phase = (t0_s + dt_s * np.arange(n)) % self.period_s
        # a sample exactly on a stage boundary belongs to the new stage; nudge against round-off
        phase = np.where(self.period_s - phase < 1e-9, 0.0, phase) + 1e-9
        for stage in self.stages:
            mask = (phase >= stage.start_s) & (phase < stage.end_s)
            for col, name in enumerate(self.relays):
                if name in stage.on:
                    out[mask, col] = 1.0
        return out


@dataclass(frozen=True)
class Resource:
    """Resource q_j consumed by machining relay ``consumer``, refilled by peripheral
    ``supplier`` (rates per second, eq. 10)."""

    name: str
    consumer: str
    supplier: str
    alpha: float
    eta: float
    q_min: float
    q_max: float
    q0: float


@dataclass(frozen=True)
class BenchProblem:
    """The machine as the controllers see it."""

    sequence: MachiningSequence
    resources: tuple[Resource, ...]
    dwell_s: dict[str, float]

    @property
    def peripherals(self) -> tuple[str, ...]:
        """Relays the controllers switch (the suppliers of the resources), in resource order."""
        return tuple(r.supplier for r in self.resources)


@dataclass
class DwellClock:
    """Each peripheral's state and when it last changed, as the controller knows it.

    ``update`` is called with every state the controller sends and every state it observes: a
    change it did not send (a safe-state, a deferral) restarts the dwell at the observation
    time, which is conservative.
    """

    state: dict[str, bool]
    changed_s: dict[str, float]

    @classmethod
    def start(cls, names: Sequence[str], state: Mapping[str, bool] | None = None
              ) -> DwellClock:
        return cls({n: bool((state or {}).get(n, False)) for n in names},
                   {n: -math.inf for n in names})

    def update(self, name: str, on: bool, t_s: float) -> None:
        if self.state[name] != on:
            self.state[name] = on
            self.changed_s[name] = t_s

    def elapsed(self, name: str, t_s: float) -> float:
        return t_s - self.changed_s[name]

    def may_switch(self, name: str, t_s: float, dwell_s: float) -> bool:
        return self.elapsed(name, t_s) >= dwell_s - 1e-6
