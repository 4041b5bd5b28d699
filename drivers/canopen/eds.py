"""The drive's own description (an EDS or DCF file, read with canopen's ``import_od``),
checked before anything is configured: every object hil reads, writes or maps must exist,
have the size hil packs, and allow what hil does with it. A drive that lacks one gets one line
naming the object and what hil needs it for."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from hil.drivers.canopen.errors import DriveError, one_line
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
from hil.protocols.cia402 import (
    CONTROLWORD,
    CYCLIC_SYNCHRONOUS_TORQUE,
    ENCODER_RESOLUTION,
    ERROR_CODE,
    MAX_TORQUE,
    MODES_DISPLAY,
    MODES_OF_OPERATION,
    POSITION_ACTUAL,
    QUICK_STOP_OPTION,
    RATED_CURRENT,
    STATUSWORD,
    SUPPORTED_MODES,
    TARGET_POSITION,
    TARGET_TORQUE,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
)

READ, WRITE, RX, TX = "read", "write", "rpdo", "tpdo"


@dataclass(frozen=True)
class Need:
    """One object hil uses: where, its size in bits, what it must allow, and why."""

    index: int
    subindex: int
    bits: int
    access: str          # READ, WRITE, RX (writable, RPDO-mappable), TX (readable, TPDO-mappable)
    why: str

    @property
    def name(self) -> str:
        return f"0x{self.index:04X}" + (f":{self.subindex}" if self.subindex else "")


def required_objects(mode: int) -> tuple[Need, ...]:
    """What the master of a drive in ``mode`` reads, writes and maps."""
    target = (Need(TARGET_TORQUE, 0, 16, RX, "to command the current every cycle")
              if mode == CYCLIC_SYNCHRONOUS_TORQUE else
              Need(TARGET_POSITION, 0, 32, RX, "to command the position every cycle"))
    return (
        Need(DEVICE_TYPE, 0, 32, READ, "to check that the node is a CiA 402 drive"),
        Need(SUPPORTED_MODES, 0, 32, READ, "to check that it supports the mode"),
        Need(MODES_OF_OPERATION, 0, 8, WRITE, "to set the mode"),
        Need(MODES_DISPLAY, 0, 8, READ, "to check the mode took effect"),
        Need(ENCODER_RESOLUTION, 1, 32, READ, "to turn increments into degrees"),
        Need(ENCODER_RESOLUTION, 2, 32, READ, "to turn increments into degrees"),
        Need(RATED_CURRENT, 0, 32, READ, "to turn per mille into mA"),
        Need(MAX_TORQUE, 0, 16, WRITE, "to set the drive's own current limit"),
        Need(QUICK_STOP_OPTION, 0, 16, WRITE, "to set the quick stop of the safe state"),
        Need(ERROR_CODE, 0, 16, READ, "to name a fault"),
        Need(CYCLE_PERIOD, 0, 32, WRITE, "to set the SYNC period"),
        Need(CONSUMER_HEARTBEAT, 1, 32, WRITE, "to make the drive watch the master"),
        Need(PRODUCER_HEARTBEAT, 0, 16, WRITE, "to watch the drive"),
        Need(CONTROLWORD, 0, 16, RX, "to switch states every cycle"),
        target,
        Need(STATUSWORD, 0, 16, TX, "for the drive's state every cycle"),
        Need(POSITION_ACTUAL, 0, 32, TX, "for the position every cycle"),
        Need(VELOCITY_ACTUAL, 0, 32, TX, "for the velocity every cycle"),
        Need(TORQUE_ACTUAL, 0, 16, TX, "for the current every cycle"),
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

    def describe(self) -> dict[str, Any]:
        return {"path": self.path, "vendor": self.vendor, "product": self.product}


def _problem(od: Any, need: Need) -> str | None:
    """Why the described object does not serve ``need`` (None: it does)."""
    if need.index not in od:
        return "is not in it"
    obj = od[need.index]
    if hasattr(obj, "subindices"):
        if need.subindex not in obj.subindices:
            return f"has no sub-index {need.subindex}"
        var = obj.subindices[need.subindex]
    elif need.subindex:
        return f"has no sub-index {need.subindex}"
    else:
        var = obj
    if var.data_type in var.STRUCT_TYPES and len(var) != need.bits:
        return f"is {len(var)} bits, hil packs {need.bits}"
    if need.access in (READ, TX) and not var.readable:
        return "is not readable"
    if need.access in (WRITE, RX) and not var.writable:
        return "is read-only"
    if need.access in (RX, TX) and not var.pdo_mappable:
        return "is not PDO-mappable"
    return None


def check(od: Any, needs: Iterable[Need]) -> list[str]:
    """Every need the object dictionary ``od`` does not meet, one line each."""
    wanted = {READ: "readable", WRITE: "writable", RX: "writable and RPDO-mappable",
              TX: "readable and TPDO-mappable"}
    return [f"{need.name} {problem}: hil needs it {wanted[need.access]}, {need.bits} bits, "
            f"{need.why}" for need in needs if (problem := _problem(od, need)) is not None]


def import_description(path: str, node_id: int) -> Any:
    """The object dictionary of the EDS/DCF at ``path`` for node ``node_id`` (canopen's
    ``import_od``); a file it cannot read is a DriveError naming it."""
    import configparser

    import canopen

    try:
        return canopen.import_od(path, node_id)
    except (OSError, ValueError, KeyError, configparser.Error) as exc:
        raise DriveError(f"cannot read its EDS {path}: {one_line(exc)}") from None


def load_description(path: str, node_id: int, needs: Iterable[Need]) -> DriveDescription:
    """The drive's EDS/DCF at ``path`` checked against ``needs``; the first unmet need is a
    DriveError naming the object, before the drive is configured or enabled."""
    try:
        od = import_description(path, node_id)
    except DriveError as exc:
        raise DriveError(f"drive node {node_id}: {exc}") from None
    problems = check(od, needs)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise DriveError(f"drive node {node_id} (EDS {path}): {problems[0]}{more}")
    info = od.device_information
    return DriveDescription(path, str(info.vendor_name or ""), str(info.product_name or ""))
