"""Object dictionary of the emulated CiA 402 drive (CiA 301 communication + CiA 402 profile).

The dictionary is a ``canopen`` :class:`~canopen.objectdictionary.ObjectDictionary` (data types,
access, limits, defaults); the drive node keeps the live values. The same dictionary serves an
independent master (``canopen.BaseNode402``) as its description of the drive.

Units: torque objects are per mille of the rated current 0x6075 (default 1000 mA, so
one unit is one mA); positions are encoder increments (0x608F, default 2^20 per revolution);
velocity is increments per second. Manufacturer objects: 0x2001 SYNC loss timeout [ms],
0x2002 over-current trip level [mA], 0x2003 external disturbance torque [mA] (a test hook),
0x2004 the counter of the SYNC the TPDOs answer (with the SYNC counter on: 0x1019 > 0), which a
master maps to bind every TPDO to its SYNC; 0x2005 the time base: 0 the drive's own clock, N > 0
the master's (SYNC time: time passes only with SYNCs, one communication cycle each), given up
after N ms of wall time without a frame (a lockstep master asks for it:
:mod:`hil.emulators.drive.node`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable
from canopen.objectdictionary.datatypes import (
    INTEGER8,
    INTEGER16,
    INTEGER32,
    UNSIGNED8,
    UNSIGNED16,
    UNSIGNED32,
    VISIBLE_STRING,
)

from hil.protocols.cia301 import (
    HIL_EMULATOR_SIGNATURE,
    HIL_EMULATOR_SUBINDEX,
    SDO_REQUEST_BASE,
    SDO_RESPONSE_BASE,
)
from hil.protocols.cia402 import (
    MODES_BY_CODE,
    NO_MODE,
    RPDOS,
    TPDOS,
    PdoMap,
)

DEVICE_TYPE = 0x0002_0192  # CiA 402 profile, servo drive
DEVICE_NAME = "hil CiA 402 drive emulator"
RTR_NOT_ALLOWED = 0x4000_0000

@dataclass(frozen=True)
class OdDefaults:
    """Start-up values of the parameters a configuration may change."""

    rated_current_ma: int = 1000
    max_torque_permille: int = 1000
    increments_per_rev: int = 1 << 20
    heartbeat_ms: int = 0
    sync_loss_timeout_ms: int = 100
    overcurrent_trip_ma: int = 15_000
    quick_stop_option: int = 2

    def per_turn(self, turns: float) -> int:
        """``turns`` axis turns [increments], as UNSIGNED32."""
        return max(1, min(0xFFFF_FFFF, round(turns * self.increments_per_rev)))


def emulator_signature() -> ODVariable:
    """0x1018:5, by which a master tells hil's drive emulator (its own dictionary or a twin)
    from a vendor's drive (:data:`~hil.protocols.cia301.HIL_EMULATOR_SIGNATURE`)."""
    return _var("hil drive emulator", 0x1018, HIL_EMULATOR_SUBINDEX, UNSIGNED32, "const",
                HIL_EMULATOR_SIGNATURE)


def _var(name: str, index: int, subindex: int, data_type: int, access: str, default: int | str,
         *, mappable: bool = False, minimum: int | None = None,
         maximum: int | None = None) -> ODVariable:
    var = ODVariable(name, index, subindex)
    var.data_type = data_type
    var.access_type = access
    var.default = default  # type: ignore[assignment]  # canopen says int; strings have str
    var.pdo_mappable = mappable
    var.min = minimum
    var.max = maximum
    return var


def _record(name: str, index: int, members: list[ODVariable], array: bool = False):
    record = ODArray(name, index) if array else ODRecord(name, index)
    for member in members:
        record.add_member(member)
    return record


def _pdo_objects(od: ObjectDictionary, node_id: int, pdo: PdoMap, tpdo: bool) -> None:
    """The communication and mapping objects of one PDO, holding the default map."""
    comm, mapping = pdo.comm, pdo.mapping
    number = comm - (0x1800 if tpdo else 0x1400) + 1
    kind = "TPDO" if tpdo else "RPDO"
    cob_default = pdo.cob_id(node_id) + (RTR_NOT_ALLOWED if tpdo else 0)
    comm_members = [
        _var("Highest sub-index supported", comm, 0, UNSIGNED8, "const", 5 if tpdo else 2),
        _var("COB-ID", comm, 1, UNSIGNED32, "rw", cob_default),
        _var("Transmission type", comm, 2, UNSIGNED8, "rw", 1),
    ]
    if tpdo:
        comm_members += [
            _var("Inhibit time", comm, 3, UNSIGNED16, "rw", 0),
            _var("Event timer", comm, 5, UNSIGNED16, "rw", 0),
        ]
    od.add_object(_record(f"{kind}{number} communication parameter", comm, comm_members))
    entries = pdo.mapping_values()
    map_members = [_var("Number of mapped objects", mapping, 0, UNSIGNED8, "rw", len(entries),
                        minimum=0, maximum=8)]
    for sub in range(1, 9):
        value = entries[sub - 1] if sub <= len(entries) else 0
        map_members.append(_var(f"Mapped object {sub}", mapping, sub, UNSIGNED32, "rw", value))
    od.add_object(_record(f"{kind}{number} mapping parameter", mapping, map_members))


def supported_modes(codes: Iterable[int]) -> int:
    """0x6502 listing the modes ``codes``."""
    return sum(MODES_BY_CODE[code].supported_bit for code in set(codes))


def build_object_dictionary(node_id: int, defaults: OdDefaults | None = None) -> ObjectDictionary:
    """The drive's object dictionary for node ``node_id`` (1..127), listing in 0x6502 every
    mode of the table, which it emulates (:data:`hil.emulators.drive.modes.MOTIONS`)."""
    if not 1 <= node_id <= 127:
        raise ValueError(f"CANopen node id must be 1..127, got {node_id}")
    d = defaults or OdDefaults()
    od = ObjectDictionary()
    od.node_id = node_id
    add = od.add_object
    add(_var("Device type", 0x1000, 0, UNSIGNED32, "ro", DEVICE_TYPE))
    add(_var("Error register", 0x1001, 0, UNSIGNED8, "ro", 0))
    add(_var("COB-ID SYNC", 0x1005, 0, UNSIGNED32, "rw", 0x80))
    add(_var("Communication cycle period", 0x1006, 0, UNSIGNED32, "rw", 0))
    add(_var("Manufacturer device name", 0x1008, 0, VISIBLE_STRING, "const", DEVICE_NAME))
    add(_var("COB-ID EMCY", 0x1014, 0, UNSIGNED32, "ro", 0x80 + node_id))
    add(_record("Consumer heartbeat time", 0x1016, [
        _var("Number of entries", 0x1016, 0, UNSIGNED8, "const", 1),
        _var("Consumer heartbeat time 1", 0x1016, 1, UNSIGNED32, "rw", 0),
    ], array=True))
    add(_var("Producer heartbeat time", 0x1017, 0, UNSIGNED16, "rw", d.heartbeat_ms))
    add(_var("Synchronous counter overflow value", 0x1019, 0, UNSIGNED8, "rw", 0,
             maximum=240))
    add(_record("SDO server parameter", 0x1200, [
        _var("Highest sub-index supported", 0x1200, 0, UNSIGNED8, "const", 2),
        _var("COB-ID client to server", 0x1200, 1, UNSIGNED32, "ro", SDO_REQUEST_BASE + node_id),
        _var("COB-ID server to client", 0x1200, 2, UNSIGNED32, "ro", SDO_RESPONSE_BASE + node_id),
    ]))
    add(_record("Identity object", 0x1018, [
        _var("Number of entries", 0x1018, 0, UNSIGNED8, "const", HIL_EMULATOR_SUBINDEX),
        _var("Vendor-ID", 0x1018, 1, UNSIGNED32, "ro", 0),
        _var("Product code", 0x1018, 2, UNSIGNED32, "ro", 0x402),
        _var("Revision number", 0x1018, 3, UNSIGNED32, "ro", 1),
        _var("Serial number", 0x1018, 4, UNSIGNED32, "ro", node_id),
        emulator_signature(),
    ]))
    for pdo in RPDOS:
        _pdo_objects(od, node_id, pdo, tpdo=False)
    for pdo in TPDOS:
        _pdo_objects(od, node_id, pdo, tpdo=True)
    add(_var("SYNC loss timeout", 0x2001, 0, UNSIGNED16, "rw", d.sync_loss_timeout_ms))
    add(_var("Over-current trip level", 0x2002, 0, UNSIGNED16, "rw", d.overcurrent_trip_ma,
             minimum=1))
    add(_var("External disturbance torque", 0x2003, 0, INTEGER16, "rw", 0, mappable=True))
    add(_var("SYNC counter echo", 0x2004, 0, UNSIGNED8, "ro", 0, mappable=True))
    add(_var("Time base", 0x2005, 0, UNSIGNED32, "rw", 0))
    add(_var("Error code", 0x603F, 0, UNSIGNED16, "ro", 0))
    add(_var("Controlword", 0x6040, 0, UNSIGNED16, "rw", 0, mappable=True))
    add(_var("Statusword", 0x6041, 0, UNSIGNED16, "ro", 0, mappable=True))
    add(_var("Quick stop option code", 0x605A, 0, INTEGER16, "rw", d.quick_stop_option))
    add(_var("Modes of operation", 0x6060, 0, INTEGER8, "rw", NO_MODE, mappable=True))
    add(_var("Modes of operation display", 0x6061, 0, INTEGER8, "ro", NO_MODE, mappable=True))
    add(_var("Position demand value", 0x6062, 0, INTEGER32, "ro", 0, mappable=True))
    add(_var("Position actual value", 0x6064, 0, INTEGER32, "ro", 0, mappable=True))
    add(_var("Following error window", 0x6065, 0, UNSIGNED32, "rw", d.per_turn(1 / 36)))
    add(_var("Position window", 0x6067, 0, UNSIGNED32, "rw", d.per_turn(1 / 3600)))
    add(_var("Position window time", 0x6068, 0, UNSIGNED16, "rw", 10))
    add(_var("Velocity demand value", 0x606B, 0, INTEGER32, "ro", 0, mappable=True))
    add(_var("Velocity actual value", 0x606C, 0, INTEGER32, "ro", 0, mappable=True))
    slow = min(0xFFFF, d.per_turn(1 / 180))  # 2 deg/s
    add(_var("Velocity window", 0x606D, 0, UNSIGNED16, "rw", slow))
    add(_var("Velocity window time", 0x606E, 0, UNSIGNED16, "rw", 10))
    add(_var("Velocity threshold", 0x606F, 0, UNSIGNED16, "rw", slow))
    add(_var("Target torque", 0x6071, 0, INTEGER16, "rw", 0, mappable=True))
    add(_var("Max torque", 0x6072, 0, UNSIGNED16, "rw", d.max_torque_permille, mappable=True))
    add(_var("Motor rated current", 0x6075, 0, UNSIGNED32, "rw", d.rated_current_ma,
             minimum=1, maximum=1_000_000))
    add(_var("Torque actual value", 0x6077, 0, INTEGER16, "ro", 0, mappable=True))
    add(_var("Target position", 0x607A, 0, INTEGER32, "rw", 0, mappable=True))
    add(_var("Home offset", 0x607C, 0, INTEGER32, "rw", 0, mappable=True))
    add(_var("Profile velocity", 0x6081, 0, UNSIGNED32, "rw", d.per_turn(1 / 4), mappable=True))
    add(_var("Profile acceleration", 0x6083, 0, UNSIGNED32, "rw", d.per_turn(1),
             mappable=True, minimum=1))
    add(_var("Profile deceleration", 0x6084, 0, UNSIGNED32, "rw", d.per_turn(1),
             mappable=True, minimum=1))
    add(_record("Position encoder resolution", 0x608F, [
        _var("Highest sub-index supported", 0x608F, 0, UNSIGNED8, "const", 2),
        _var("Encoder increments", 0x608F, 1, UNSIGNED32, "ro", d.increments_per_rev),
        _var("Motor revolutions", 0x608F, 2, UNSIGNED32, "ro", 1),
    ]))
    add(_var("Homing method", 0x6098, 0, INTEGER8, "rw", 37, mappable=True))
    add(_record("Homing speeds", 0x6099, [
        _var("Highest sub-index supported", 0x6099, 0, UNSIGNED8, "const", 2),
        _var("Speed during search for switch", 0x6099, 1, UNSIGNED32, "rw", d.per_turn(1 / 4),
             mappable=True),
        _var("Speed during search for zero", 0x6099, 2, UNSIGNED32, "rw", d.per_turn(1 / 36),
             mappable=True),
    ], array=True))
    add(_var("Homing acceleration", 0x609A, 0, UNSIGNED32, "rw", d.per_turn(2), mappable=True,
             minimum=1))
    add(_var("Digital inputs", 0x60FD, 0, UNSIGNED32, "ro", 0, mappable=True))
    add(_var("Target velocity", 0x60FF, 0, INTEGER32, "rw", 0, mappable=True))
    add(_var("Supported drive modes", 0x6502, 0, UNSIGNED32, "ro",
             supported_modes(MODES_BY_CODE)))
    return od


def iter_variables(od: ObjectDictionary):
    """Every variable of ``od`` (sub-indices of records and arrays included)."""
    for index in od:
        obj = od[index]
        if isinstance(obj, ODVariable):
            yield obj
        else:
            for sub in obj:
                yield obj[sub]
