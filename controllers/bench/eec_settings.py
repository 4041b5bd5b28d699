"""What the EEC's horizon solvers are tuned by (:class:`EECSettings`) and what one solve gives
back (:class:`SolveResult`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hil.controllers.bench.eec_choices import SOLVERS, TERMINALS


@dataclass(frozen=True)
class EECSettings:
    """Tuning of the EEC (``[eec]`` of ``hil/configs/eec.toml`` documents each)."""

    hp_steps: int = 28
    hs_steps: int = 1
    step_s: float = 1.0
    gamma1: float = 0.9
    gamma2: float = 0.1
    gamma3: float = 0.0        # cost of one switch-on (relay wear), in units of J
    terminal: str = "hold"
    limit_va: float | None = None
    limit_weight: float = 10.0
    peak_resolution_va: float = 1.0
    time_limit_s: float = 1.0
    mip_rel_gap: float = 1e-4
    solver: str = "dp"         # "dp": exact schedule DP (2 peripherals); "milp": HiGHS

    def __post_init__(self) -> None:
        if self.hp_steps < 1 or self.hs_steps < 1 or self.hs_steps > self.hp_steps:
            raise ValueError(f"need 1 <= H_s <= H_p, got H_s = {self.hs_steps}, "
                             f"H_p = {self.hp_steps}")
        if self.terminal not in TERMINALS:
            raise ValueError(f"terminal must be one of {TERMINALS}, got {self.terminal!r}")
        if self.gamma1 < 0 or self.gamma2 < 0 or self.gamma1 + self.gamma2 <= 0:
            raise ValueError("gamma1, gamma2 must be >= 0 and not both 0")
        if self.gamma3 < 0:
            raise ValueError(f"gamma3 must be >= 0, got {self.gamma3}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {self.solver!r}")


@dataclass
class SolveResult:
    status: str                # "optimal", "time_limit", "infeasible", "error: ..."
    u: np.ndarray | None       # devices x H, 0/1
    objective: float
    peak_va: float             # z: the plan's predicted highest point
    solve_ms: float
    rows: int                  # J2 pattern rows
    warm_start: bool
    levels: int = 0            # J2 level binaries
    gap: float = 0.0           # relative MIP gap at the end (0: proven optimal)
    nodes: int = 0             # branch-and-bound nodes (MILP) or partial plans kept (DP)
    bound: float = math.nan    # proven lower bound of the objective

