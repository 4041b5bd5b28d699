"""One object of a drive read or written by SDO (``hil drive sdo``), typed by the drive's
EDS (canopen's ``import_od``) or by a type name; values are decoded and encoded by canopen's
``ODVariable``. A write to an object a valid PDO carries is refused while the drive is
operational (NMT OPERATIONAL by its heartbeat, or OPERATION ENABLED by 0x6041): the cyclic
exchange owns it then, and a value written beside it would be overwritten, or fight it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

from canopen.objectdictionary import ODVariable, datatypes

from hil.drivers.canopen.eds import import_description
from hil.drivers.canopen.errors import DriveError
from hil.drivers.canopen.link import Link
from hil.drivers.canopen.scan import frames_within, nmt_state_name, read_pdos
from hil.drivers.canopen.sdo import SdoChannel, SdoClient
from hil.drivers.errors import DriverSetupError
from hil.protocols.cia301 import (
    HEARTBEAT_BASE,
    NMT_OPERATIONAL,
    NMT_STATE_NAMES,
    PRODUCER_HEARTBEAT,
    SdoAbortError,
)
from hil.protocols.cia402 import OPERATION_ENABLED, STATUSWORD, state_of

CIA_TYPES = ("BOOLEAN", "INTEGER8", "INTEGER16", "INTEGER32", "INTEGER64", "UNSIGNED8",
             "UNSIGNED16", "UNSIGNED32", "UNSIGNED64", "REAL32", "REAL64", "VISIBLE_STRING",
             "OCTET_STRING")
SHORT_TYPES = {"u8": "UNSIGNED8", "u16": "UNSIGNED16", "u32": "UNSIGNED32",
               "u64": "UNSIGNED64", "i8": "INTEGER8", "i16": "INTEGER16", "i32": "INTEGER32",
               "i64": "INTEGER64", "f32": "REAL32", "f64": "REAL64", "bool": "BOOLEAN",
               "str": "VISIBLE_STRING"}
TYPE_CODES = {name: getattr(datatypes, name) for name in CIA_TYPES}
TYPE_NAMES = {code: name for name, code in TYPE_CODES.items()}
TYPE_HELP = (", ".join(SHORT_TYPES) + " or the CiA 301 names " + ", ".join(CIA_TYPES)
             + " (case does not matter)")
WRITE_SIZES = {1: "<B", 2: "<H", 4: "<I"}  # what an expedited download carries
HEARTBEAT_LISTEN_MAX_S = 3.0


def parse_type(text: str) -> int:
    """A type name (``u16``, ``UNSIGNED16``...) as canopen's data type code."""
    name = SHORT_TYPES.get(text.lower(), text.upper())
    if name not in TYPE_CODES:
        raise ValueError(f"unknown type {text!r} (expected {TYPE_HELP})")
    return TYPE_CODES[name]


def parse_object(text: str) -> tuple[int, int]:
    """``INDEX[:SUB]``: the index in hex (``0x6041`` or ``6041``), the sub-index decimal or
    ``0x``-hex (default 0)."""
    index_text, colon, sub_text = text.partition(":")
    try:
        index = int(index_text, 16)
        subindex = int(sub_text, 0) if colon else 0
    except ValueError:
        raise ValueError(f"expected INDEX[:SUB] such as 0x6041 or 0x1018:1, got {text!r}"
                         ) from None
    if not 0 <= index <= 0xFFFF or not 0 <= subindex <= 0xFF:
        raise ValueError(f"{text!r}: the index is 0x0000..0xFFFF, the sub-index 0..255")
    return index, subindex


def object_name(index: int, subindex: int) -> str:
    return f"0x{index:04X}:{subindex}"


def eds_type(path: str, node_id: int, index: int, subindex: int) -> int:
    """The data type the EDS at ``path`` gives object ``index:subindex``."""
    var = import_description(path, node_id).get_variable(index, subindex)
    if var is None:
        raise DriverSetupError(f"{object_name(index, subindex)} is not in the EDS {path} (give "
                         "--type)")
    code: int = var.data_type
    return code


def _variable(index: int, subindex: int, data_type: int) -> ODVariable:
    var = ODVariable(object_name(index, subindex), index, subindex)
    var.data_type = data_type
    return var


@dataclass(frozen=True)
class ObjectValue:
    """One object as read: its bytes, and its value when a type says how to read them (without
    one, the unsigned value of 1, 2, 4 or 8 bytes)."""

    node_id: int
    index: int
    subindex: int
    raw: bytes
    data_type: int | None

    def __post_init__(self) -> None:
        """Bytes of another size than the type's are said here, in one line."""
        if self.data_type is None:
            return
        var = _variable(self.index, self.subindex, self.data_type)
        if self.data_type in var.STRUCT_TYPES and len(self.raw) * 8 != len(var):
            raise DriverSetupError(
                f"drive node {self.node_id}: {object_name(self.index, self.subindex)}"
          f" has {len(self.raw)} bytes ({self.raw.hex(' ')}), "
          f"{self.type_name} is {len(var) // 8}")

    @property
    def type_name(self) -> str | None:
        return None if self.data_type is None else TYPE_NAMES.get(self.data_type,
                                                                  f"0x{self.data_type:04X}")

    @property
    def value(self) -> Any:
        if self.data_type is None:
            return int.from_bytes(self.raw, "little") if len(self.raw) in (1, 2, 4, 8) else None
        value = _variable(self.index, self.subindex, self.data_type).decode_raw(self.raw)
        return value.hex() if isinstance(value, (bytes, bytearray)) else value

    def as_dict(self) -> dict[str, Any]:
        return {"node": self.node_id, "object": object_name(self.index, self.subindex),
                "index": self.index, "subindex": self.subindex, "type": self.type_name,
                "size": len(self.raw), "hex": self.raw.hex(), "value": self.value}

    def describe(self) -> str:
        """``node 1 0x6041:0 UNSIGNED16 = 592 (0x0250)``, or untyped
        ``node 1 0x6041:0 = 50 02 (2 bytes, unsigned 592)``."""
        where = f"node {self.node_id} {object_name(self.index, self.subindex)}"
        value = self.value
        if self.data_type is None:
            unsigned = "" if value is None else f", unsigned {value}"
            return f"{where} = {self.raw.hex(' ') or '(empty)'} ({len(self.raw)} bytes{unsigned})"
        if isinstance(value, str):
            return f"{where} {self.type_name} = {value!r}"
        if isinstance(value, bool) or not isinstance(value, int):
            return f"{where} {self.type_name} = {value}"
        return f"{where} {self.type_name} = {value} (0x{self.raw[::-1].hex().upper()})"


def encode(text: str, data_type: int) -> bytes:
    """``text`` as the bytes of ``data_type`` (a DriverSetupError says why it cannot be)."""
    name = TYPE_NAMES.get(data_type, f"0x{data_type:04X}")
    var = _variable(0, 0, data_type)
    try:
        value: Any
        if data_type in datatypes.INTEGER_TYPES:
            value = int(text, 0)
        elif data_type in datatypes.FLOAT_TYPES:
            value = float(text)
        elif data_type == datatypes.BOOLEAN:
            value = {"0": False, "1": True, "false": False, "true": True}[text.lower()]
        elif data_type == datatypes.OCTET_STRING:
            value = bytes.fromhex(text)
        else:
            value = text
        return bytes(var.encode_raw(value))
    except (ValueError, KeyError, UnicodeError, struct.error):
        bits = len(var) if data_type in var.STRUCT_TYPES else 0
        signed = data_type in datatypes.SIGNED_TYPES
        span = (f" ({-(1 << (bits - 1))}..{(1 << (bits - 1)) - 1})" if signed else
                f" (0..{(1 << bits) - 1})") if data_type in datatypes.INTEGER_TYPES else ""
        raise DriverSetupError(f"VALUE {text!r} is not a valid {name}{span}") from None


def download_format(raw: bytes) -> str:
    """The struct format of an expedited download of ``raw`` (1, 2 or 4 bytes; else a
    DriverSetupError)."""
    if len(raw) not in WRITE_SIZES:
        raise DriverSetupError(f"hil drive sdo write sends 1, 2 or 4 bytes (an expedited SDO "
                         f"download); this value is {len(raw)}")
    return WRITE_SIZES[len(raw)]


def read_object(sdo: SdoChannel, index: int, subindex: int, data_type: int | None
                ) -> ObjectValue:
    """Upload ``index:subindex`` (an SdoAbortError names the drive's abort code)."""
    return ObjectValue(sdo.node_id, index, subindex, sdo.read(index, subindex), data_type)


def heard_nmt_state(link: Link, node_id: int, period_ms: int) -> str | None:
    """The NMT state of the node's next heartbeat, listened for two periods and a margin (at
    most :data:`HEARTBEAT_LISTEN_MAX_S`)."""
    listen_s = min(2 * period_ms / 1000 + 0.25, HEARTBEAT_LISTEN_MAX_S)
    for can_id, data in frames_within(link, listen_s):
        if can_id == HEARTBEAT_BASE + node_id and data:
            return nmt_state_name(data)
    return None


def _optional_int(sdo: SdoClient, index: int, fmt: str) -> int | None:
    try:
        return sdo.read_int(index, 0, fmt)
    except SdoAbortError:
        return None


def operational(link: Link, sdo: SdoClient) -> str | None:
    """Why the drive counts as operational (``OPERATION ENABLED (0x6041)``, ``NMT OPERATIONAL
    (its heartbeat)``), or None."""
    statusword = _optional_int(sdo, STATUSWORD, "<H")
    if statusword is not None and state_of(statusword) == OPERATION_ENABLED:
        return f"{OPERATION_ENABLED} (0x6041 = 0x{statusword:04X})"
    period_ms = _optional_int(sdo, PRODUCER_HEARTBEAT, "<H")
    if period_ms and heard_nmt_state(link, sdo.node_id, period_ms) == \
            NMT_STATE_NAMES[NMT_OPERATIONAL]:
        return "NMT OPERATIONAL (its heartbeat)"
    return None


def write_object(link: Link, sdo: SdoClient, index: int, subindex: int, raw: bytes) -> None:
    """Download ``raw`` to ``index:subindex`` (expedited: 1, 2 or 4 bytes), unless a valid PDO
    carries it while the drive is operational (a DriveError saying so)."""
    fmt = download_format(raw)
    name = object_name(index, subindex)
    carriers = [pdo.name for pdo in read_pdos(sdo) if pdo.valid and pdo.maps(index, subindex)]
    if carriers:
        why = operational(link, sdo)
        if why is not None:
            raise DriveError(f"drive node {sdo.node_id}: not written: {name} is mapped in "
                             f"{', '.join(carriers)} and the drive is {why}; the cyclic "
                             "exchange owns it until the run stops")
    sdo.write(index, subindex, int.from_bytes(raw, "little"), fmt)
