"""A mode's set point on the wire: hil's unit (:attr:`OperationMode.unit`: ``deg`` for a
position, ``deg/s`` for a velocity, ``mA`` for a current) turned into the drive's number
(increments, increments/s, per mille of the rated current) by the drive's scaling, and the
set point that holds the axis where it stands (the target of configure and of a stop).

A position is sent in the frame the drive reports its position in: the master counts turns
where the drive's position wraps (:class:`~hil.drivers.canopen.cyclic.CyclicExchange`), and a
target goes back through the same count, so a multi-turn drive gets its absolute target and
a drive that counts one turn gets one on its turn."""

from __future__ import annotations

import math
from collections.abc import Callable

from hil.drivers.canopen.errors import DriveError
from hil.drivers.canopen.scaling import DriveScaling
from hil.protocols.cia402 import OperationMode

#: what a set point of each size may hold on the wire
WIRE_RANGE = {16: (-(1 << 15), (1 << 15) - 1), 32: (-(1 << 31), (1 << 31) - 1)}


def wire_value(mode: OperationMode, value: float, scaling: DriveScaling, turns: int,
               node_id: int) -> int:
    """``value`` (a position [deg], multi-turn, or a velocity [deg/s]) as the drive's number
    for ``mode``'s set point; ``turns``: the turns the master has counted on the drive's
    position (see the module). A current is not converted here: the master clamps it first.
    A value that is not finite, or that the set point cannot hold, is a DriveError."""
    if mode.set_point is None:
        return 0
    if not math.isfinite(value):
        raise DriveError(f"drive node {node_id}: refusing a non-finite {mode.title} set point "
                         f"({value!r})")
    counts = scaling.counts(value)
    if mode.unit == "deg":
        counts -= turns * scaling.counts_per_turn
    low, high = WIRE_RANGE[mode.set_point[2]]
    if not low <= counts <= high:
        raise DriveError(f"drive node {node_id}: {mode.title} set point {value:g} {mode.unit} "
                         f"is {counts} on the wire, beyond what 0x{mode.set_point[0]:04X} holds")
    return counts


def holding_value(mode: OperationMode, position: Callable[[], int | None]) -> int:
    """The set point that holds the axis where it stands: in a position mode its position
    (``position()``, the drive's raw 0x6064, asked only then; None: unknown, 0), no velocity
    or current in the others."""
    if mode.unit != "deg":
        return 0
    raw = position()
    return 0 if raw is None else raw


def wire_format(mode: OperationMode) -> str:
    """The SDO format of ``mode``'s set point (``<h`` for 16 bits, ``<i`` for 32)."""
    assert mode.set_point is not None
    return "<h" if mode.set_point[2] == 16 else "<i"
