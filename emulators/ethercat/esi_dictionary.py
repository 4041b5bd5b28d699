"""A vendor's ESI file (ETG.2000) read as a CoE object dictionary: its first device's
``<Profile><Dictionary>`` as the canopen :class:`~canopen.objectdictionary.ObjectDictionary`
an EDS gives, so that the twin (:mod:`hil.emulators.drive.twin`) is built from either by the
same rules (values left empty come from ``set``, modes from 0x6502, a refusal naming the
deciding reason). Its PDO mapping objects (0x1600.., 0x1A00..) are the dictionary's where it
has them and the ``<RxPdo>`` / ``<TxPdo>`` elements' where it does not (an entry the
dictionary leaves empty is the element's); a ``Fixed`` PDO's map is read-only.

ESI's ``DefaultData`` is the value's bytes in hexadecimal, least significant first
(``e5030f00`` is 0x000F03E5); an object or sub-item without one is empty, as an EDS entry
without a DefaultValue. Types are IEC 61131 names (``UDINT``, ``INT``...), an object of
several sub-items a ``DataType`` with ``SubItem`` children; a sub-item of an array type
(``ArrayInfo``) stands for its elements, sub-index 1 on."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from typing import Any

from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable
from canopen.objectdictionary.datatypes import (
    BOOLEAN,
    INTEGER8,
    INTEGER16,
    INTEGER32,
    INTEGER64,
    OCTET_STRING,
    REAL32,
    REAL64,
    UNSIGNED8,
    UNSIGNED16,
    UNSIGNED32,
    UNSIGNED64,
    VISIBLE_STRING,
)

from hil.emulators.errors import EmulatorSetupError
from hil.emulators.ethercat.esi import sii_from_esi
from hil.emulators.ethercat.sii import PdoSpec

#: ESI's base types (ETG.2000, IEC 61131 names) as CANopen's
BASE_TYPES = {
    "BOOL": BOOLEAN, "BIT": BOOLEAN, "SINT": INTEGER8, "INT": INTEGER16, "DINT": INTEGER32,
    "LINT": INTEGER64, "USINT": UNSIGNED8, "BYTE": UNSIGNED8, "UINT": UNSIGNED16,
    "WORD": UNSIGNED16, "UDINT": UNSIGNED32, "DWORD": UNSIGNED32, "ULINT": UNSIGNED64,
    "REAL": REAL32, "LREAL": REAL64}
ACCESS = {"ro": "ro", "rw": "rw", "wo": "wo"}
STRING = re.compile(r"^STRING\(\d+\)$")


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _child(element: ET.Element | None, name: str) -> ET.Element | None:
    if element is None:
        return None
    return next((child for child in element if _local(child.tag) == name), None)


def _children(element: ET.Element | None, name: str) -> list[ET.Element]:
    return [] if element is None else [c for c in element if _local(c.tag) == name]


def _text(element: ET.Element | None, name: str) -> str | None:
    found = _child(element, name)
    return found.text.strip() if found is not None and found.text else None


def _number(text: str) -> int:
    return int(text[2:], 16) if text[:2] in ("#x", "#X") else int(text)


def esi_dictionary(path: str) -> ET.Element | None:
    """The first device's ``<Dictionary>`` of the ESI file at ``path`` (None: it has none)."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise EmulatorSetupError(f"ESI {path}: cannot read it ({exc})") from None
    device = _child(_child(_child(root, "Descriptions"), "Devices"), "Device")
    return _child(_child(device, "Profile"), "Dictionary")


def od_from_esi(path: str, node_id: int) -> ObjectDictionary:
    """The CoE objects of the ESI file at ``path`` as canopen's dictionary (node ``node_id``);
    a file without a ``<Dictionary>`` is an EmulatorSetupError saying so."""
    dictionary = esi_dictionary(path)
    if dictionary is None:
        raise EmulatorSetupError(f"ESI {path}: its device has no <Profile><Dictionary> (no "
                                 "CoE objects to build a twin from)")
    types = {name: element for element in _children(_child(dictionary, "DataTypes"),
                                                    "DataType")
             if (name := _text(element, "Name"))}
    od = ObjectDictionary()
    od.node_id = node_id
    for element in _children(_child(dictionary, "Objects"), "Object"):
        try:
            obj = _object(element, types)
        except (ValueError, TypeError) as exc:
            raise EmulatorSetupError(f"ESI {path}: object {_text(element, 'Index')}: "
                                     f"{exc}") from None
        if obj is not None:
            od.add_object(obj)
    content = sii_from_esi(path)
    for pdo in (*content.rx_pdos, *content.tx_pdos):
        _pdo_mapping(od, pdo)
    return od


def _pdo_mapping(od: ObjectDictionary, pdo: PdoSpec) -> None:
    """The mapping object of an ``<RxPdo>`` / ``<TxPdo>``: the dictionary's, its sub-indices
    left empty given the element's entries; made from the element where the dictionary lacks
    it; read-only where the element says its map is ``Fixed``."""
    entries = pdo.mapping_values()
    record = od.get(pdo.index)
    if record is None:
        record = ODRecord(pdo.name or f"PDO 0x{pdo.index:04X}", pdo.index)
        for sub in range(len(entries) + 1):
            var = ODVariable(f"{record.name} {sub}" if sub else "Number of entries",
                             pdo.index, sub)
            var.data_type, var.access_type = (UNSIGNED32, "rw") if sub else (UNSIGNED8, "rw")
            record.add_member(var)
        od.add_object(record)
    if isinstance(record, ODVariable):
        return  # not a mapping object: the twin refuses its type
    for sub, var in record.subindices.items():
        if var.default is None:
            var.default = len(entries) if sub == 0 else \
                entries[sub - 1] if sub <= len(entries) else 0
        if pdo.fixed:
            var.access_type = "ro"


def _object(element: ET.Element, types: dict[str, ET.Element]
            ) -> ODVariable | ODRecord | ODArray | None:
    index = _number(_text(element, "Index") or "")
    name = _text(element, "Name") or f"0x{index:04X}"
    type_name = _text(element, "Type") or ""
    info = _child(element, "Info")
    flags = _child(element, "Flags")
    structure = types.get(type_name)
    items = _children(structure, "SubItem")
    if not items:
        data_type = _data_type(type_name, types)
        if data_type is None:
            return None  # a type the twin has no use for: like an object the file lacks
        return _variable(name, index, 0, data_type, flags, _text(info, "DefaultData"))
    record = ODRecord(name, index)
    values = [_text(_child(sub, "Info"), "DefaultData") for sub in _children(info, "SubItem")]
    subindex = 0
    for item in items:
        item_type = _text(item, "Type") or ""
        array = types.get(item_type)
        if array is not None and _child(array, "ArrayInfo") is not None:
            base = _data_type(_text(array, "BaseType") or "", types)
            elements = int(_text(_child(array, "ArrayInfo"), "Elements") or 0)
            for _ in range(elements):  # sub-indices from the one after sub-index 0 on
                if base is not None:
                    record.add_member(_variable(
                        f"{name} {subindex}", index, subindex, base, _child(item, "Flags"),
                        values[subindex] if subindex < len(values) else None))
                subindex += 1
            continue
        if _text(item, "SubIdx") is not None:
            subindex = _number(_text(item, "SubIdx") or "0")
        data_type = _data_type(item_type, types)
        if data_type is not None:
            record.add_member(_variable(
                _text(item, "Name") or f"{name} {subindex}", index, subindex, data_type,
                _child(item, "Flags"), values[subindex] if subindex < len(values) else None))
        subindex += 1
    return record


def _data_type(name: str, types: dict[str, ET.Element]) -> int | None:
    """CANopen's type for ESI's ``name`` (an enum or alias by its ``BaseType``)."""
    if name in BASE_TYPES:
        return BASE_TYPES[name]
    if STRING.match(name):
        return VISIBLE_STRING
    if name.startswith("ARRAY [") or name == "OCTET_STRING":
        return OCTET_STRING
    alias = types.get(name)
    base = _text(alias, "BaseType") if alias is not None else None
    if base is not None and _child(alias, "ArrayInfo") is None and base != name:
        return _data_type(base, types)
    return None


def _variable(name: str, index: int, subindex: int, data_type: int,
              flags: ET.Element | None, data: str | None) -> ODVariable:
    var = ODVariable(name, index, subindex)
    var.data_type = data_type
    var.access_type = ACCESS.get((_text(flags, "Access") or "ro").lower(), "ro")
    var.pdo_mappable = _text(flags, "PdoMapping") is not None
    if data:
        var.default = _decoded(var, bytes.fromhex(data))
    return var


def _decoded(var: ODVariable, raw: bytes) -> Any:
    """DefaultData's bytes as the value of ``var``'s type."""
    if var.data_type == VISIBLE_STRING:
        return raw.decode("latin-1")
    if var.data_type == OCTET_STRING:
        return raw
    if var.data_type in (REAL32, REAL64):
        return var.decode_raw(raw)
    signed = var.data_type in (INTEGER8, INTEGER16, INTEGER32, INTEGER64)
    return int.from_bytes(raw, "little", signed=signed)
