"""The ``[relays]`` table of the bench config, validated once for both sides of the wire: the
driver (coils, safe levels, dwell) and the emulator (which coil is which relay)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from hil.core.config import lookup
from hil.core.errors import ConfigError

SOURCE = "bench config"


@dataclass(frozen=True)
class RelaySpec:
    """One relay: its coil on the relay module, safe level and minimum on/off time."""

    name: str
    coil: int
    safe: bool
    dwell_s: float


def relay_specs(config: Mapping[str, Any]) -> dict[str, RelaySpec]:
    """``{name: RelaySpec}`` from ``[relays]``: coils >= 0 and distinct, dwell finite >= 0."""
    table = lookup(config, "relays", dict, source=SOURCE)
    if not table:
        raise ConfigError(f"{SOURCE}: [relays] is empty: name at least one relay")
    relays: dict[str, RelaySpec] = {}
    for name in table:
        coil = lookup(config, f"relays.{name}.coil", int, source=SOURCE)
        dwell = lookup(config, f"relays.{name}.dwell_s", float, 5.0, source=SOURCE)
        if coil < 0 or not 0 <= dwell < math.inf:
            raise ConfigError(f"{SOURCE}: relay {name}: coil must be >= 0 and dwell_s "
                              f"a finite number >= 0, got coil={coil}, dwell_s={dwell}")
        clash = next((r.name for r in relays.values() if r.coil == coil), None)
        if clash:
            raise ConfigError(f"{SOURCE}: relays {clash} and {name} are both on coil {coil}")
        safe = lookup(config, f"relays.{name}.safe", bool, False, source=SOURCE)
        relays[name] = RelaySpec(name, coil, safe, dwell)
    return relays
