"""The ``[sweep]`` table of ``--sweep-config F.toml``: the same space as the flags, in a file.

::

    [sweep]
    workers = 2             # optional: --workers, --address, --seed
    [sweep.grid]            # KEY = [values]: the Cartesian product
    ert = ["zoh", "foh"]
    "param.gain" = [1, 2]
    [sweep.random]          # trials = N, KEY = [lo, hi]
    trials = 4
    umax = [300, 1000]

Flags given on the command line win over the file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hil.core.config import Table, load_toml
from hil.errors import ConfigError


@dataclass
class SweepTable:
    """The parsed ``[sweep]`` table; values still as the file wrote them."""

    grid: dict[str, list[Any]] = field(default_factory=dict)
    ranges: dict[str, tuple[Any, Any]] = field(default_factory=dict)
    random_trials: int = 0
    seed: int | None = None
    workers: int | None = None
    address: str | None = None


def load_sweep_table(path: str) -> SweepTable:
    data, _text = load_toml(path)
    if "sweep" not in data:
        raise ConfigError(f"{path}: no [sweep] table")
    root = Table(data, path)
    sweep = root.table("sweep")
    table = SweepTable(seed=sweep.integer("seed", None),
                       workers=sweep.integer("workers", None, above=0),
                       address=sweep.get("address", str, None))
    grid = sweep.table("grid")
    for key in grid.names():
        values = grid.get(key, list)
        if not values:
            raise grid.error(key, "must list at least one value")
        table.grid[key] = values
    grid.done()
    rand = sweep.table("random")
    table.random_trials = rand.integer("trials", 0, at_least=0)
    for key in rand.names():
        if key == "trials":
            continue
        bounds = rand.get(key, list)
        if len(bounds) != 2:
            raise rand.error(key, "must be [lo, hi]")
        table.ranges[key] = (bounds[0], bounds[1])
    rand.done()
    if table.ranges and not table.random_trials:
        raise rand.error("trials", "must be set (> 0) with ranges to sample")
    sweep.done()
    root.done()
    return table
