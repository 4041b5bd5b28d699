"""The objects that shape a mode's profile (the mode table's ``profile``: profile velocity,
acceleration and deceleration of PP and PV; homing method, offset, speeds and acceleration of
HM), as configure writes them: converted from hil's units (deg, deg/s, deg/s^2) to the
drive's, for the values configured (``[profile]``, ``[homing]``; None keeps the drive's own).
A value configured for an object the drive lacks is refused: it could not take effect."""

from __future__ import annotations

import struct

from hil.drivers.canopen.config import PROFILE_KEYS, ProfileSettings
from hil.drivers.canopen.errors import DriveError
from hil.drivers.canopen.objects import DriveObjects
from hil.drivers.canopen.scaling import DriveScaling
from hil.protocols.cia402 import PROFILE_OBJECTS, OperationMode

#: (index, sub-index, value, format) of one object written by SDO
Write = tuple[int, int, int, str]


def profile_writes(objects: DriveObjects, mode: OperationMode, settings: ProfileSettings,
                   scaling: DriveScaling) -> list[Write]:
    """What configure writes of ``mode``'s profile: each configured value in the drive's
    units (a DriveError, before anything is written, for a value the drive cannot take)."""
    writes = []
    n = objects.sdo.node_id
    for index, subindex in mode.profile:
        value = settings.value_of(index, subindex)
        if value is None:
            continue
        shape, key = PROFILE_OBJECTS[index, subindex], PROFILE_KEYS[index, subindex][1]
        name = f"0x{index:04X}" + (f":{subindex}" if subindex else "")
        if not objects.has(index, subindex):
            raise DriveError(f"drive node {n} has no {name} ({shape.title}): {key} = "
                             f"{value:g} cannot take effect; leave it out to keep the drive's "
                             "own")
        raw = scaling.counts(value) if shape.unit else round(value)
        try:
            struct.pack(shape.fmt, raw)
        except struct.error:
            raise DriveError(f"drive node {n}: {key} = {value:g} is {raw} on the wire, beyond "
                             f"what {name} ({shape.title}) holds") from None
        writes.append((index, subindex, raw, shape.fmt))
    return writes
