"""The motion of each mode of operation the emulated drive runs, by the mode table
(:data:`hil.protocols.cia402.OPERATION_MODES`): one :class:`~hil.emulators.drive.motion.ModeMotion`
per mode, each in a module of its own."""

from __future__ import annotations

from hil.emulators.drive.cyclic import CyclicPosition, CyclicTorque, CyclicVelocity
from hil.emulators.drive.homing import Homing
from hil.emulators.drive.motion import Axis, ModeMotion
from hil.emulators.drive.profile_position import ProfilePosition
from hil.emulators.drive.profile_velocity import ProfileVelocity
from hil.protocols.cia402 import OPERATION_MODES

#: the motion of every mode in the table, by the mode's name there
MOTIONS: dict[str, type[ModeMotion]] = {
    "pp": ProfilePosition, "pv": ProfileVelocity, "hm": Homing,
    "csp": CyclicPosition, "csv": CyclicVelocity, "cst": CyclicTorque,
}
#: the 0x6060 codes of the modes the emulated drive runs
EMULATED_MODES: tuple[int, ...] = tuple(sorted(OPERATION_MODES[name].code for name in MOTIONS))


def mode_motions(axis: Axis) -> dict[int, ModeMotion]:
    """Each emulated mode's motion on ``axis``, by its 0x6060 code."""
    return {OPERATION_MODES[name].code: motion(axis) for name, motion in MOTIONS.items()}
