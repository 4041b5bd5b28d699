"""The current a master may send a drive: the smallest of the run's limit and the drive's own,
read before anything is written (a limit only ever tightens on its way to the drive).

* the run's limit: ``current_limit_mA`` of the master's config (lowered by a flag, never raised
  unless the user said so);
* 0x6073 max current and 0x6072 max torque as the drive holds them, per mille of its rated
  current (0x6075; hil reads the torque objects as current), each optional in CiA 402; for a
  drive without 0x6072, ``[master] max_torque_permille`` stands in for it (the drive's own
  torque limit, set by other means).

The master writes the result to 0x6072 for the session, where the drive has it, and puts the
drive's own value back when it lets the drive go, so one run's limit never becomes the next
one's. Without 0x6072 the drive cannot be given the run's limit: hil's own clamp is the only
limit of the current it commands (:attr:`CurrentLimit.unenforced` says so).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

from hil.drivers.canopen.errors import DriveError
from hil.drivers.canopen.objects import DriveObjects, StandIn, drive_or_config
from hil.drivers.canopen.scaling import DriveScaling
from hil.protocols.cia402 import MAX_CURRENT, MAX_TORQUE, OperationMode

#: the key that stands in for 0x6072 on a drive without it
MAX_TORQUE_STAND_IN = StandIn(MAX_TORQUE, 0, "max torque [per mille of the rated current]",
                              "max_torque_permille")


@dataclass(frozen=True)
class CurrentLimit:
    """Each link of the chain [mA] (None: the drive has no such object) and the raw 0x6072
    found, to put back."""

    run_ma: float
    max_current_ma: float | None   # 0x6073
    max_torque_ma: float | None    # 0x6072 as found
    max_torque_found: int | None   # its raw per mille (None: the drive has no 0x6072)
    max_torque_from: str = "0x6072"  # where max_torque_ma came from: 0x6072 or the key

    @property
    def unenforced(self) -> bool:
        """The drive has no 0x6072: the run's limit cannot be given to it."""
        return self.max_torque_found is None

    @cached_property
    def applied_ma(self) -> float:
        """The smallest link: what the master clamps every command to (worked out once: it is
        read twice a tick for every axis)."""
        return min(v for v in (self.run_ma, self.max_current_ma, self.max_torque_ma)
                   if v is not None)

    def describe(self) -> dict[str, Any]:
        return {"applied_mA": self.applied_ma, "run_mA": self.run_ma,
                "drive_max_current_mA": self.max_current_ma,
                "drive_max_torque_mA": self.max_torque_ma}

    def text(self) -> str:
        """``300 mA: the run's 300 mA, the drive's max current (0x6073) 2000 mA, ...``."""
        links = [f"the run's {self.run_ma:g} mA"]
        for name, value in (("max current (0x6073)", self.max_current_ma),
                            (f"max torque ({self.max_torque_from})", self.max_torque_ma)):
            links.append(f"the drive's {name} " + ("-" if value is None else f"{value:g} mA"))
        return f"{self.applied_ma:g} mA, the smallest of " + ", ".join(links)


def read_current_limit(objects: DriveObjects, scaling: DriveScaling, run_ma: float,
                       max_torque_permille: int | None = None) -> CurrentLimit:
    """The chain of ``run_ma`` and the drive's 0x6073 / 0x6072 (or the key that stands in for
    0x6072, ``max_torque_permille``), read by SDO where the drive has them."""
    current = objects.read(MAX_CURRENT, 0, "<H")
    torque, torque_from = drive_or_config(objects, MAX_TORQUE_STAND_IN, max_torque_permille,
                                          "<H")
    if torque is None:
        return CurrentLimit(run_ma, None if current is None else scaling.milliamps(current),
                            None, None)
    found = int(torque) if torque_from == MAX_TORQUE_STAND_IN.name else None
    return CurrentLimit(run_ma, None if current is None else scaling.milliamps(current),
                        scaling.milliamps(torque), found, torque_from)


def unenforced_text(node_id: int, mode: OperationMode, limit: CurrentLimit) -> str:
    """What a drive without 0x6072 means for a run in ``mode``: in a current mode hil's clamp
    is the only limit of the current it commands; in the others the drive chooses the current
    and only its own limits hold."""
    head = (f"drive node {node_id} has no 0x6072 (max torque): the run's limit of "
            f"{limit.run_ma:g} mA cannot be given to the drive; ")
    if mode.unit == "mA":
        return head + f"hil's clamp ({limit.applied_ma:g} mA) is the only limit of the current"
    return head + (f"in {mode.short} the drive chooses the current, and only its own limits "
                   "hold")


def max_torque_units(limit: CurrentLimit, scaling: DriveScaling, node_id: int) -> int:
    """0x6072 for a run: the applied limit rounded up to a torque unit, never above what the
    drive held."""
    rated = scaling.rated_current_ma
    units = math.ceil(limit.applied_ma * 1000.0 / rated - 1e-9)
    if limit.max_torque_found is not None:
        units = min(units, limit.max_torque_found)
    if units > 0xFFFF:
        raise DriveError(f"drive node {node_id}: current limit {limit.applied_ma:g} mA is "
                         f"beyond what 0x6072 can hold with a rated current of {rated:g} mA")
    return units
