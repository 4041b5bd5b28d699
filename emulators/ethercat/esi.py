"""A vendor's ESI file (ETG.2000, EtherCAT Slave Information XML) as the emulated slave's SII:
the first device's identity (vendor id, product code, revision), name, SyncManagers (start,
default size, control byte), its default RxPDOs and TxPDOs and its CoE details. The drive
behind it stays hil's (or a twin of the drive's EDS): its objects and PDO maps are what the
mailbox serves and what a master assigns.

Numbers are ESI's: ``#x1A00`` hexadecimal, else decimal."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from hil.emulators.errors import EmulatorSetupError
from hil.emulators.ethercat.sii import (
    DEFAULT_SYNC_MANAGERS,
    PdoEntrySpec,
    PdoSpec,
    SiiContent,
    SyncManagerSpec,
)
from hil.protocols.cia402 import RPDO1, TPDO_LAYOUTS
from hil.protocols.ethercat import (
    COE_COMPLETE_ACCESS,
    COE_PDO_ASSIGN,
    COE_PDO_CONFIG,
    COE_SDO,
    COE_SDO_INFO,
)

SM_USES = {"MBoxOut": 1, "MBoxIn": 2, "Outputs": 3, "Inputs": 4}
COE_FLAGS = {"SdoInfo": COE_SDO_INFO, "PdoAssign": COE_PDO_ASSIGN, "PdoConfig": COE_PDO_CONFIG,
             "CompleteAccess": COE_COMPLETE_ACCESS}


def esi_number(text: str | None, what: str, default: int | None = None) -> int:
    """``#x1A00`` or ``6656``; a missing value is ``default`` (or an error naming ``what``)."""
    if text is None or not text.strip():
        if default is None:
            raise EmulatorSetupError(f"ESI: no {what}")
        return default
    text = text.strip()
    try:
        return int(text[2:], 16) if text[:2] in ("#x", "#X") else int(text)
    except ValueError:
        raise EmulatorSetupError(f"ESI: {what} {text!r} is not a number (#x1A00 or 6656)") from None


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _child(element: ET.Element, name: str) -> ET.Element | None:
    return next((child for child in element if _local(child.tag) == name), None)


def _children(element: ET.Element, name: str) -> list[ET.Element]:
    return [child for child in element if _local(child.tag) == name]


def sii_from_esi(path: str) -> SiiContent:
    """The SII of the first device of the ESI file at ``path``; a file that is not one is a
    ConfigError naming what is wrong."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise EmulatorSetupError(f"ESI {path}: cannot read it ({exc})") from None
    if _local(root.tag) != "EtherCATInfo":
        raise EmulatorSetupError(f"ESI {path}: the root element is <{_local(root.tag)}>, not "
                          "<EtherCATInfo>")
    vendor = _child(root, "Vendor")
    descriptions = _child(root, "Descriptions")
    devices = _child(descriptions, "Devices") if descriptions is not None else None
    device = _child(devices, "Device") if devices is not None else None
    if vendor is None or device is None:
        raise EmulatorSetupError(f"ESI {path}: no <Vendor> or no <Descriptions><Devices><Device>")
    kind = _child(device, "Type")
    if kind is None:
        raise EmulatorSetupError(f"ESI {path}: the device has no <Type>")
    name = _child(device, "Name")
    return SiiContent(
        vendor_id=esi_number(_text(_child(vendor, "Id")), "vendor <Id>"),
        product_code=esi_number(kind.get("ProductCode"), "ProductCode"),
        revision=esi_number(kind.get("RevisionNo"), "RevisionNo", 0),
        serial=0,
        name=(_text(name) or kind.text or "").strip() or "ESI device",
        sync_managers=_sync_managers(device),
        rx_pdos=tuple(_pdo(pdo, 2) for pdo in _children(device, "RxPdo")),
        tx_pdos=tuple(_pdo(pdo, 3) for pdo in _children(device, "TxPdo")),
        coe_details=_coe_details(device),
        source=f"ESI {Path(path).name}")


def _text(element: ET.Element | None) -> str | None:
    return element.text if element is not None else None


def _sync_managers(device: ET.Element) -> tuple[SyncManagerSpec, ...]:
    found = []
    for number, sm in enumerate(_children(device, "Sm")):
        use = SM_USES.get((sm.text or "").strip(), DEFAULT_SYNC_MANAGERS[min(number, 3)].use)
        size = sm.get("DefaultSize") or sm.get("MaxSize") or ("128" if use <= 2 else "0")
        found.append(SyncManagerSpec(esi_number(sm.get("StartAddress"), "Sm StartAddress"),
                                     esi_number(size, "Sm DefaultSize"),
                                     esi_number(sm.get("ControlByte"), "Sm ControlByte"), use))
    uses = {sm.use for sm in found}
    if not {1, 2} <= uses:
        return DEFAULT_SYNC_MANAGERS  # no mailbox described: hil's layout
    return tuple(found)


def _pdo(pdo: ET.Element, sync_manager: int) -> PdoSpec:
    """An ``<RxPdo>`` (``sync_manager`` 2) or ``<TxPdo>`` (3): assigned to its ``Sm`` at
    power-on where it names one."""
    entries = []
    for entry in _children(pdo, "Entry"):
        entries.append(PdoEntrySpec(esi_number(_text(_child(entry, "Index")), "Entry Index"),
                                    esi_number(_text(_child(entry, "SubIndex")), "SubIndex", 0),
                                    esi_number(_text(_child(entry, "BitLen")), "BitLen")))
    return PdoSpec(esi_number(_text(_child(pdo, "Index")), "Pdo Index"),
                   esi_number(pdo.get("Sm"), "Pdo Sm", sync_manager), tuple(entries),
                   (_text(_child(pdo, "Name")) or "").strip(), assigned=pdo.get("Sm") is not None,
                   fixed=_flag(pdo.get("Fixed")), mandatory=_flag(pdo.get("Mandatory")),
                   excludes=tuple(esi_number(_text(exclude), "Exclude")
                                  for exclude in _children(pdo, "Exclude")))


def _flag(text: str | None) -> bool:
    """An ESI boolean: ``1`` or ``true``."""
    return (text or "").strip().lower() in ("1", "true")


def _coe_details(device: ET.Element) -> int:
    mailbox = _child(device, "Mailbox")
    coe = _child(mailbox, "CoE") if mailbox is not None else None
    if coe is None:
        return COE_SDO | COE_PDO_ASSIGN | COE_PDO_CONFIG
    details = COE_SDO
    for attribute, flag in COE_FLAGS.items():
        if _flag(coe.get(attribute)):
            details |= flag
    return details & ~COE_COMPLETE_ACCESS  # the emulated mailbox does not serve it


def fixed_pdo_problems(path: str) -> list[str]:
    """One line for each PDO of the ESI file at ``path`` that hil's master maps its own objects
    into (:data:`~hil.protocols.cia402.RPDO1`, the TxPDOs of every ``[master] tpdo_layout``)
    and the file fixes: hil remaps PDOs; it does not adopt a fixed map."""
    content = sii_from_esi(path)
    mapped = {RPDO1.mapping} | {pdo.mapping for layout in TPDO_LAYOUTS.values()
                                for pdo in layout}
    return [f"{kind} 0x{pdo.index:04X} ({pdo.name or 'no name'}) is Fixed: hil's master maps "
            "its own objects into it (hil remaps PDOs; it does not adopt a fixed map)"
            for kind, pdos in (("RxPDO", content.rx_pdos), ("TxPDO", content.tx_pdos))
            for pdo in pdos if pdo.fixed and pdo.index in mapped]
