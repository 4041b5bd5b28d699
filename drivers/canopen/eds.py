"""The drive's own description (an EDS or DCF file, read with canopen's ``import_od``),
checked before anything is configured: every object hil needs must exist, and every object
hil uses that the file has must have the size hil packs and allow what hil does with it. An
object hil can do without (CiA 402 makes most of them optional) may be missing: it is then
neither read nor written (:class:`~hil.drivers.canopen.objects.DriveObjects`), its value
coming from the ``[master]`` key that stands in for it, or hil doing without it. A drive
that lacks a needed one gets one line naming the object and what hil needs it for; a file
that lists no mode hil drives says that first."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hil.drivers.canopen.errors import DriveError, one_line
from hil.drivers.canopen.objects import DOING_WITHOUT, described
from hil.protocols.cia301 import (
    CONSUMER_HEARTBEAT,
    CYCLE_PERIOD,
    DEVICE_TYPE,
    PRODUCER_HEARTBEAT,
    RPDO_COMM_BASE,
    RPDO_MAP_BASE,
    TPDO_COMM_BASE,
    TPDO_MAP_BASE,
)
from hil.protocols.cia306 import description_encoding
from hil.protocols.cia402 import (
    CONTROLWORD,
    ENCODER_RESOLUTION,
    ERROR_CODE,
    MAX_TORQUE,
    MODE_SHORT_NAMES,
    MODES_BY_CODE,
    MODES_DISPLAY,
    MODES_OF_OPERATION,
    POSITION_ACTUAL,
    PROFILE_OBJECTS,
    QUICK_STOP_OPTION,
    RATED_CURRENT,
    STATUSWORD,
    SUPPORTED_MODES,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
    OperationMode,
    supported_mode_bit,
)

READ, WRITE, RX, TX = "read", "write", "rpdo", "tpdo"


@dataclass(frozen=True)
class Need:
    """One object hil uses: where, its size in bits, what it must allow, and why;
    ``without``: how hil does without it when the drive lacks it ("": it cannot)."""

    index: int
    subindex: int
    bits: int
    access: str          # READ, WRITE, RX (writable, RPDO-mappable), TX (readable, TPDO-mappable)
    why: str
    without: str = ""

    @property
    def name(self) -> str:
        return f"0x{self.index:04X}" + (f":{self.subindex}" if self.subindex else "")


#: what a set point of each unit commands
SET_POINTS = {"mA": "current", "deg": "position", "deg/s": "velocity"}


def _without(index: int, subindex: int = 0) -> str:
    return DOING_WITHOUT[index, subindex][1]


def objects_used(mode: OperationMode) -> tuple[Need, ...]:
    """What the master of a drive in ``mode`` reads, writes and maps."""
    set_point = () if mode.set_point is None else (
        Need(*mode.set_point, RX, f"to command the {SET_POINTS[str(mode.unit)]} every cycle"),)
    return (
        Need(DEVICE_TYPE, 0, 32, READ, "to check that the node is a CiA 402 drive"),
        Need(SUPPORTED_MODES, 0, 32, READ, "to check that it supports the mode",
             _without(SUPPORTED_MODES)),
        Need(MODES_OF_OPERATION, 0, 8, WRITE, "to set the mode"),
        Need(MODES_DISPLAY, 0, 8, READ, "to check the mode took effect"),
        Need(ENCODER_RESOLUTION, 1, 32, READ, "to turn increments into degrees",
             "[master] increments_per_rev stands in"),
        Need(ENCODER_RESOLUTION, 2, 32, READ, "to turn increments into degrees",
             "one motor revolution"),
        Need(RATED_CURRENT, 0, 32, READ, "to turn per mille into mA",
             "[master] rated_current_mA stands in"),
        Need(MAX_TORQUE, 0, 16, WRITE, "to set the drive's own current limit",
             "hil's clamp is the only limit of the current it commands"),
        Need(QUICK_STOP_OPTION, 0, 16, WRITE, "to set the quick stop of the safe state",
             _without(QUICK_STOP_OPTION)),
        Need(ERROR_CODE, 0, 16, READ, "to name a fault", _without(ERROR_CODE)),
        Need(CYCLE_PERIOD, 0, 32, WRITE, "to set the SYNC period", _without(CYCLE_PERIOD)),
        Need(CONSUMER_HEARTBEAT, 1, 32, WRITE, "to make the drive watch the master",
             _without(CONSUMER_HEARTBEAT, 1)),
        Need(PRODUCER_HEARTBEAT, 0, 16, WRITE, "to watch the drive",
             _without(PRODUCER_HEARTBEAT)),
        Need(CONTROLWORD, 0, 16, RX, "to switch states every cycle"),
        *set_point,
        *(Need(index, sub, PROFILE_OBJECTS[index, sub].bits, WRITE,
               f"for the {PROFILE_OBJECTS[index, sub].title}",
               "the drive's own value (a value configured for it is refused)")
          for index, sub in mode.profile),
        Need(STATUSWORD, 0, 16, TX, "for the drive's state every cycle"),
        Need(POSITION_ACTUAL, 0, 32, TX, "for the position every cycle"),
        Need(VELOCITY_ACTUAL, 0, 32, TX, "for the velocity every cycle"),
        Need(TORQUE_ACTUAL, 0, 16, TX, "for the current every cycle", _without(TORQUE_ACTUAL)),
        *(Need(base, 1, 32, WRITE, "to set up the cyclic PDOs")
          for base in (RPDO_COMM_BASE, TPDO_COMM_BASE, TPDO_COMM_BASE + 1)),
        *(Need(base, 0, 8, WRITE, "to set up the cyclic PDOs")
          for base in (RPDO_MAP_BASE, TPDO_MAP_BASE, TPDO_MAP_BASE + 1)),
    )


@dataclass(frozen=True)
class DriveDescription:
    """What the EDS says about the drive, once checked."""

    path: str
    vendor: str
    product: str
    od: Any = field(default=None, repr=False, compare=False)  # canopen's object dictionary

    def describe(self) -> dict[str, Any]:
        return {"path": self.path, "vendor": self.vendor, "product": self.product}


def _problem(od: Any, need: Need) -> str | None:
    """Why the described object does not serve ``need`` (None: it does, or it is missing and
    hil can do without it)."""
    if not described(od, need.index, need.subindex):
        if need.without:
            return None
        return "is not in it" if need.index not in od else f"has no sub-index {need.subindex}"
    obj = od[need.index]
    var = obj.subindices[need.subindex] if hasattr(obj, "subindices") else obj
    if var.data_type in var.STRUCT_TYPES and len(var) != need.bits:
        return f"is {len(var)} bits, hil packs {need.bits}"
    if need.access in (READ, TX) and not var.readable:
        return "is not readable"
    if need.access in (WRITE, RX) and not var.writable:
        return "is read-only"
    if need.access in (RX, TX) and not var.pdo_mappable:
        return "is not PDO-mappable"
    return None


def check(od: Any, mode: OperationMode) -> list[str]:
    """Every reason the object dictionary ``od`` does not serve a drive in ``mode``, one line
    each, the deciding one first: the modes its 0x6502 lists, then each need it does not
    meet."""
    wanted = {READ: "readable", WRITE: "writable", RX: "writable and RPDO-mappable",
              TX: "readable and TPDO-mappable"}
    problems = [problem] if (problem := mode_problem(od, mode)) is not None else []
    return problems + [f"{need.name} {problem}: hil needs it {wanted[need.access]}, "
                       f"{need.bits} bits, {need.why}"
                       for need in objects_used(mode)
                       if (problem := _problem(od, need)) is not None]


def listed_modes(od: Any) -> int | None:
    """The 0x6502 supported modes a description gives (its default value; None: the file
    has no 0x6502, or no value for it)."""
    if not described(od, SUPPORTED_MODES, 0):
        return None
    value = od[SUPPORTED_MODES].default
    return int(value) if isinstance(value, int) else None


def mode_problem(od: Any, mode: OperationMode) -> str | None:
    """Why the description's 0x6502 rules ``mode`` out (None: it lists it, or nothing)."""
    listed = listed_modes(od)
    return None if listed is None else modes_problem(listed, mode)


def modes_problem(supported: int, mode: OperationMode) -> str | None:
    """Why a drive whose 0x6502 holds ``supported`` cannot be driven in ``mode`` (None: it
    can): it supports no mode hil drives, or others than ``mode``, named."""
    if supported & mode.supported_bit:
        return None
    names = [short for code, short in MODE_SHORT_NAMES.items()
             if supported & supported_mode_bit(code)]
    hil_drives = [m.short for m in MODES_BY_CODE.values() if supported & m.supported_bit]
    if not hil_drives:
        return (f"supports no mode hil drives ({', '.join(names) or 'none'}: 0x6502 = "
                f"0x{supported:08X}; hil drives "
                f"{', '.join(m.short for m in MODES_BY_CODE.values())})")
    return (f"mode {mode.short} not supported (it supports {', '.join(names)}: 0x6502 = "
            f"0x{supported:08X}); hil drives it in {', '.join(hil_drives)} ([master] mode)")


def import_description(path: str, node_id: int) -> Any:
    """The object dictionary of the EDS/DCF at ``path`` for node ``node_id`` (canopen's
    ``import_od``, of its text in its encoding); a file it cannot read is a DriveError naming
    it."""
    import configparser

    import canopen

    try:
        with open(path, encoding=description_encoding(path)) as text:
            return canopen.import_od(text, node_id)
    except (OSError, ValueError, KeyError, configparser.Error) as exc:
        raise DriveError(f"cannot read its EDS {path}: {one_line(exc)}") from None


def load_description(path: str, node_id: int, mode: OperationMode) -> DriveDescription:
    """The drive's EDS/DCF at ``path`` checked for ``mode``; the first problem (the deciding
    one: the modes it lists) is a DriveError naming it, before the drive is configured or
    enabled."""
    try:
        od = import_description(path, node_id)
    except DriveError as exc:
        raise DriveError(f"drive node {node_id}: {exc}") from None
    problems = check(od, mode)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise DriveError(f"drive node {node_id} (EDS {path}): {problems[0]}{more}")
    info = od.device_information
    return DriveDescription(path, str(info.vendor_name or ""), str(info.product_name or ""),
                            od)
