"""How the drive's numbers become degrees and milliamps: read from the drive, never assumed.

* position: 0x608F encoder increments per motor revolution (sub 1 / sub 2), 0x6091 gear ratio
  (motor revolutions per shaft revolution; 1:1 when the drive has no 0x6091): one turn of the
  axis is ``increments * motor_revolutions / shaft_revolutions`` counts of 0x6064;
* current: 0x6071 and 0x6077 are per mille of the rated current 0x6075 (mA);
* polarity: 0x607E is applied by the drive itself; it is read to be recorded.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import cached_property
from typing import Any

from hil.drivers.canopen.errors import DriveError
from hil.drivers.canopen.sdo import SdoClient
from hil.protocols.cia301 import ABORT_NO_OBJECT, ABORT_NO_SUBINDEX, SdoAbortError
from hil.protocols.cia402 import ENCODER_RESOLUTION, GEAR_RATIO, POLARITY, RATED_CURRENT


@dataclass(frozen=True)
class DriveScaling:
    """The drive's units."""

    increments_per_rev: int = 1 << 20   # 0x608F: encoder increments per motor revolution
    motor_revolutions: int = 1          # 0x6091 sub 1
    shaft_revolutions: int = 1          # 0x6091 sub 2
    rated_current_ma: float = 1000.0    # 0x6075
    polarity: int = 0                   # 0x607E

    @cached_property  # read every cycle; the scaling never changes once read
    def counts_per_turn(self) -> int:
        """0x6064 counts in one turn of the axis."""
        return self.increments_per_rev * self.motor_revolutions // self.shaft_revolutions

    @cached_property
    def degrees_per_count(self) -> float:
        return 360.0 / self.counts_per_turn

    def degrees(self, counts: float) -> float:
        """Counts of 0x6064 (or 0x606C per second) as degrees of the axis."""
        return counts * self.degrees_per_count

    def counts(self, degrees: float) -> int:
        return round(degrees / 360.0 * self.counts_per_turn)

    def milliamps(self, per_mille: float) -> float:
        """A torque object's per mille of the rated current as mA."""
        return per_mille * self.rated_current_ma / 1000.0

    def per_mille(self, milliamps: float) -> int:
        return round(milliamps * 1000.0 / self.rated_current_ma)

    def describe(self) -> dict[str, Any]:
        """For the session's metadata and ``hil drive scan``."""
        return asdict(self) | {"counts_per_turn": self.counts_per_turn}


def optional_object(sdo: SdoClient, index: int, subindex: int, fmt: str) -> int | None:
    """An object the drive may not have (CiA 402 makes it optional): None when it has not."""
    try:
        return sdo.read_int(index, subindex, fmt)
    except SdoAbortError as exc:
        if exc.code in (ABORT_NO_OBJECT, ABORT_NO_SUBINDEX):
            return None
        raise


def _optional(sdo: SdoClient, index: int, subindex: int, fmt: str, default: int) -> int:
    value = optional_object(sdo, index, subindex, fmt)
    return default if value is None else value


def read_scaling(sdo: SdoClient) -> DriveScaling:
    """The drive's scaling by SDO; an unusable value is a DriveError naming the object."""
    n = sdo.node_id
    increments = sdo.read_int(ENCODER_RESOLUTION, 1)
    motor_turns = sdo.read_int(ENCODER_RESOLUTION, 2)
    if not increments or motor_turns != 1:
        raise DriveError(f"drive node {n}: encoder resolution 0x608F = {increments} "
                         f"increments / {motor_turns} revolutions is not supported (hil needs "
                         "increments per one motor revolution)")
    rated = sdo.read_int(RATED_CURRENT, 0)
    if not rated:
        raise DriveError(f"drive node {n}: rated current 0x6075 is 0 mA: the torque objects "
                         "would mean nothing")
    gear_motor = _optional(sdo, GEAR_RATIO, 1, "<I", 1)
    gear_shaft = _optional(sdo, GEAR_RATIO, 2, "<I", 1)
    if not gear_motor or not gear_shaft:
        raise DriveError(f"drive node {n}: gear ratio 0x6091 = {gear_motor}:{gear_shaft} has a "
                         "zero")
    polarity = _optional(sdo, POLARITY, 0, "<B", 0)
    return DriveScaling(increments, gear_motor, gear_shaft, float(rated), polarity)
