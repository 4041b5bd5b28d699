"""What the bench's controllers know about the machine (energy paper, sections II and IV).

* the machining sequence Lambda_M (Assumption 1: known a priori): a periodic table of stages,
  each naming the machining relays that are on;
* the peripherals P_j and their resources q_j (eq. 10, Table I): q_j(k+1) = q_j(k) +
  alpha_j [consumer on] + eta_j u_Pj(k) per second, with operating bounds;
* the minimum on/off dwell of every peripheral relay.

Read from the bench config (``[sequence]``, ``[plant.resources]``, ``[relays]``): the resource
table sits under ``[plant]`` because the emulator integrates the same relation; on a real bench
it is the process knowledge of Table I. Pure data, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil.core.config import lookup
from hil.core.errors import ConfigError

SOURCE = "bench config"


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


def parse_sequence(config: Mapping[str, Any]) -> MachiningSequence:
    """``[sequence]`` of the bench config: stages tiling ``[0, period_s)`` in order, each
    naming relays of ``[relays]`` (the one parser of the table; the bridge plays it from it)."""
    period = lookup(config, "sequence.period_s", float, source=SOURCE)
    raw = lookup(config, "sequence.stages", list, source=SOURCE)
    known = lookup(config, "relays", dict, source=SOURCE)
    if not period > 0 or not raw:
        raise ConfigError(f"{SOURCE}: [sequence] needs period_s > 0 and at least one stage")
    stages: list[Stage] = []
    expected_start = 0.0
    for i, entry in enumerate(raw):
        where = f"{SOURCE}: sequence.stages[{i}]"
        if not isinstance(entry, Mapping):
            raise ConfigError(f"{where} must be a table {{start_s, end_s, on}}")
        start = lookup(entry, "start_s", float, source=where)
        end = lookup(entry, "end_s", float, source=where)
        on = lookup(entry, "on", list, source=where)
        if abs(start - expected_start) > 1e-9 or not end > start:
            raise ConfigError(f"{where}: stages must tile [0, period) in order: expected "
                              f"start_s = {expected_start:g} < end_s, got {start:g}..{end:g}")
        unknown = [n for n in on if n not in known]
        if unknown:
            raise ConfigError(f"{where}: unknown relay(s) {unknown} (relays: "
                              f"{', '.join(known)})")
        stages.append(Stage(start, end, frozenset(on)))
        expected_start = end
    if abs(expected_start - period) > 1e-9:
        raise ConfigError(f"{SOURCE}: sequence stages end at {expected_start:g} s, "
                          f"not at period_s = {period:g} s")
    relays = tuple(sorted(set().union(*(stage.on for stage in stages))))
    return MachiningSequence(period, tuple(stages), relays)


def parse_resources(config: Mapping[str, Any], sequence: MachiningSequence
                    ) -> tuple[Resource, ...]:
    table = lookup(config, "plant.resources", dict, source=SOURCE)
    resources = []
    for name in table:
        key = f"plant.resources.{name}"
        consumer = lookup(config, f"{key}.consumer", str, source=SOURCE)
        supplier = lookup(config, f"{key}.supplier", str, source=SOURCE)
        if consumer not in sequence.relays:
            raise ConfigError(f"{SOURCE}: key '{key}.consumer' = {consumer!r} is not a relay of "
                              f"the machining sequence ({', '.join(sequence.relays)})")
        if supplier in sequence.relays:
            raise ConfigError(f"{SOURCE}: key '{key}.supplier' = {supplier!r} is a machining "
                              "relay; a supplier must be a peripheral")
        bounds = lookup(config, f"{key}.bounds", list, source=SOURCE)
        if len(bounds) != 2 or not all(isinstance(b, (int, float)) for b in bounds) or \
                not bounds[0] < bounds[1]:
            raise ConfigError(f"{SOURCE}: key '{key}.bounds' must be [low, high], got {bounds!r}")
        eta = lookup(config, f"{key}.eta", float, source=SOURCE)
        if not eta > 0:
            raise ConfigError(f"{SOURCE}: key '{key}.eta' must be > 0, got {eta}")
        resources.append(Resource(
            name, consumer, supplier, lookup(config, f"{key}.alpha", float, source=SOURCE), eta,
            float(bounds[0]), float(bounds[1]), lookup(config, f"{key}.q0", float, source=SOURCE),
        ))
    if not resources:
        raise ConfigError(f"{SOURCE}: [plant.resources] is empty: the controllers need q_j")
    suppliers = [r.supplier for r in resources]
    if len(set(suppliers)) != len(suppliers):
        raise ConfigError(f"{SOURCE}: each peripheral may supply one resource only")
    return tuple(resources)


def load_problem(config: Mapping[str, Any], dwell_s: float | None = None) -> BenchProblem:
    """The :class:`BenchProblem` of a bench config; ``dwell_s`` overrides every dwell."""
    sequence = parse_sequence(config)
    resources = parse_resources(config, sequence)
    dwell = {}
    for r in resources:
        value = lookup(config, f"relays.{r.supplier}.dwell_s", float, 5.0, source=SOURCE)
        dwell[r.supplier] = float(dwell_s) if dwell_s is not None else value
        if dwell[r.supplier] < 0:
            raise ConfigError(f"{SOURCE}: dwell of {r.supplier} must be >= 0")
    return BenchProblem(sequence, resources, dwell)


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
