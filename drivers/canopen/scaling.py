"""How the drive's numbers become degrees and milliamps: read from the drive, never assumed;
for a drive without an object, the ``[master]`` key that stands in for it.

* position: 0x608F encoder increments per motor revolution (sub 1 / sub 2; ``[master]
  increments_per_rev`` where the drive has no 0x608F), 0x6091 gear ratio (motor revolutions
  per shaft revolution; 1:1 when the drive has no 0x6091): one turn of the axis is
  ``increments * motor_revolutions / shaft_revolutions`` counts of 0x6064;
* current: 0x6071 and 0x6077 are per mille of the rated current 0x6075 (mA; ``[master]
  rated_current_mA`` where the drive has none);
* polarity: 0x607E is applied by the drive itself; it is read to be recorded.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import cached_property
from typing import Any

from hil.drivers.canopen.errors import DriveError
from hil.drivers.canopen.objects import DriveObjects, StandIn, drive_or_config
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


#: the keys that stand in for the scaling objects a drive lacks
INCREMENTS = StandIn(ENCODER_RESOLUTION, 1, "encoder increments per motor revolution",
                     "increments_per_rev")
RATED = StandIn(RATED_CURRENT, 0, "rated current [mA], what the torque objects are per mille "
                "of", "rated_current_mA")


def read_scaling(objects: DriveObjects, increments_per_rev: int | None = None,
                 rated_current_ma: float | None = None) -> tuple[DriveScaling, dict[str, str]]:
    """The drive's scaling, by SDO where it has the objects, else from the keys that stand in
    for them (``increments_per_rev``, ``rated_current_ma``), and where each value came from
    (``{"increments_per_rev": "0x608F:1", "rated_current_ma": "[master] rated_current_mA"}``).
    A value neither has, or one that cannot be used, is a DriveError naming the object."""
    n = objects.sdo.node_id
    increments, increments_from = drive_or_config(objects, INCREMENTS, increments_per_rev)
    if increments is None:
        raise INCREMENTS.missing(n)
    motor_turns = objects.read(ENCODER_RESOLUTION, 2) if increments_from == INCREMENTS.name \
        else 1
    if not increments or motor_turns not in (1, None):
        raise DriveError(f"drive node {n}: encoder resolution 0x608F = {increments} "
                         f"increments / {motor_turns} revolutions is not supported (hil needs "
                         "increments per one motor revolution)")
    rated, rated_from = drive_or_config(objects, RATED, rated_current_ma)
    if rated is None:
        raise RATED.missing(n)
    if not rated:
        raise DriveError(f"drive node {n}: rated current 0x6075 is 0 mA: the torque objects "
                         "would mean nothing")
    gear_motor = _or(objects.read(GEAR_RATIO, 1), 1)
    gear_shaft = _or(objects.read(GEAR_RATIO, 2), 1)
    if not gear_motor or not gear_shaft:
        raise DriveError(f"drive node {n}: gear ratio 0x6091 = {gear_motor}:{gear_shaft} has a "
                         "zero")
    polarity = _or(objects.read(POLARITY, 0, "<B"), 0)
    return (DriveScaling(int(increments), gear_motor, gear_shaft, float(rated), polarity),
            {"increments_per_rev": increments_from, "rated_current_ma": rated_from})


def _or(value: int | None, default: int) -> int:
    return default if value is None else value
