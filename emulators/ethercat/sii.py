"""The slave's SII EEPROM (ETG.1000.6 / ETG.2010): the words a master reads before anything
else (identity, mailbox, protocols) and the categories behind them (strings, general with the
CoE details, FMMU uses, SyncManagers, default PDOs), built from a :class:`SiiContent`: hil's
defaults (the drive's 0x1018 and PDO maps) or a vendor's ESI file
(:mod:`hil.emulators.ethercat.esi`)."""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

from hil.protocols.cia402 import mapping_entry
from hil.protocols.ethercat import (
    CAT_END,
    CAT_FMMU,
    CAT_GENERAL,
    CAT_RXPDO,
    CAT_STRINGS,
    CAT_SYNC_MANAGER,
    CAT_TXPDO,
    COE_PDO_ASSIGN,
    COE_PDO_CONFIG,
    COE_SDO,
    FMMU_USE_INPUTS,
    FMMU_USE_MAILBOX_STATE,
    FMMU_USE_OUTPUTS,
    MAILBOX_COE,
    SII_CATEGORIES,
    SII_MAILBOX_PROTOCOLS,
    SII_RX_MAILBOX,
    SII_SIZE,
    SII_VENDOR,
    SII_VERSION,
    SM_TYPE_INPUTS,
    SM_TYPE_MAILBOX_IN,
    SM_TYPE_MAILBOX_OUT,
    SM_TYPE_OUTPUTS,
)

SII_BYTES = 2048              # a 16 kbit EEPROM
PDI_CONTROL = 0x0005          # the PDI the ESC reports (SPI slave; the emulator has none)
MAILBOX_SIZE = 128


@dataclass(frozen=True)
class SyncManagerSpec:
    """One SyncManager as the SII describes it: physical start, default length, control
    byte, its use (:data:`~hil.protocols.ethercat.SM_TYPE_OUTPUTS`...)."""

    start: int
    length: int
    control: int
    use: int


@dataclass(frozen=True)
class PdoEntrySpec:
    index: int
    subindex: int
    bits: int
    data_type: int = 0


@dataclass(frozen=True)
class PdoSpec:
    """A PDO's default mapping: its index (0x1600.. RxPDO, 0x1A00.. TxPDO), its
    SyncManager, its entries; as an ESI describes it besides: ``assigned`` to that
    SyncManager at power-on (its ``Sm``), its map ``fixed``, ``mandatory`` (assigned in
    SAFE-OP and OP), the PDOs it ``excludes`` (never assigned with it)."""

    index: int
    sync_manager: int
    entries: tuple[PdoEntrySpec, ...]
    name: str = ""
    assigned: bool = True
    fixed: bool = False
    mandatory: bool = False
    excludes: tuple[int, ...] = ()

    def mapping_values(self) -> list[int]:
        """The mapping object's sub-indices 1..n (index, sub-index, bits)."""
        return [mapping_entry(entry.index, entry.subindex, entry.bits) for entry in self.entries]


#: SM0/SM1 the mailbox, SM2 outputs (3 buffers, watchdog), SM3 inputs: the usual layout
DEFAULT_SYNC_MANAGERS = (
    SyncManagerSpec(0x1000, MAILBOX_SIZE, 0x26, SM_TYPE_MAILBOX_OUT),
    SyncManagerSpec(0x1080, MAILBOX_SIZE, 0x22, SM_TYPE_MAILBOX_IN),
    SyncManagerSpec(0x1100, 0, 0x64, SM_TYPE_OUTPUTS),
    SyncManagerSpec(0x1180, 0, 0x20, SM_TYPE_INPUTS),
)


@dataclass(frozen=True)
class SiiContent:
    """What the EEPROM says of the slave."""

    vendor_id: int
    product_code: int
    revision: int
    serial: int
    name: str
    sync_managers: tuple[SyncManagerSpec, ...] = DEFAULT_SYNC_MANAGERS
    rx_pdos: tuple[PdoSpec, ...] = ()
    tx_pdos: tuple[PdoSpec, ...] = ()
    coe_details: int = COE_SDO | COE_PDO_ASSIGN | COE_PDO_CONFIG
    source: str = "hil's defaults"
    group: str = field(default="Drives")

    def mailbox(self, use: int) -> SyncManagerSpec:
        return next(sm for sm in self.sync_managers if sm.use == use)


def crc8(data: bytes) -> int:
    """The SII header's checksum (CRC-8, polynomial 0x07, initial 0xFF) over words 0-6."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def _category(kind: int, data: bytes) -> bytes:
    if len(data) % 2:
        data += b"\0"
    return struct.pack("<HH", kind, len(data) // 2) + data


def _strings(names: list[str]) -> bytes:
    out = bytearray([len(names)])
    for name in names:
        raw = name.encode("ascii", "replace")[:255]
        out += bytes([len(raw)]) + raw
    return bytes(out)


def _pdos(pdos: tuple[PdoSpec, ...], name_index: int) -> bytes:
    out = bytearray()
    for pdo in pdos:
        out += struct.pack("<HBBBBH", pdo.index, len(pdo.entries), pdo.sync_manager, 0,
                           name_index, 0)
        for entry in pdo.entries:
            out += struct.pack("<HBBBBH", entry.index, entry.subindex, 0, entry.data_type,
                               entry.bits, 0)
    return bytes(out)


def build_sii(content: SiiContent) -> bytes:
    """The EEPROM image: the header words, then the categories, then 0xFF."""
    words = bytearray(SII_CATEGORIES * 2)
    struct.pack_into("<H", words, 0, PDI_CONTROL)
    words[14] = crc8(bytes(words[:14]))
    struct.pack_into("<IIII", words, SII_VENDOR * 2, content.vendor_id, content.product_code,
                     content.revision, content.serial)
    rx, tx = content.mailbox(SM_TYPE_MAILBOX_OUT), content.mailbox(SM_TYPE_MAILBOX_IN)
    struct.pack_into("<HHHH", words, SII_RX_MAILBOX * 2, rx.start, rx.length, tx.start,
                     tx.length)
    struct.pack_into("<H", words, SII_MAILBOX_PROTOCOLS * 2, MAILBOX_COE)
    struct.pack_into("<H", words, SII_SIZE * 2, SII_BYTES * 8 // 1024 - 1)
    struct.pack_into("<H", words, SII_VERSION * 2, 1)
    # strings: 1 the device's name, 2 its group
    general = bytearray(32)
    general[0], general[3] = 2, 1          # group, name (string numbers)
    general[5] = content.coe_details
    general[9] = 1                          # one CiA 402 axis
    categories = [
        _category(CAT_STRINGS, _strings([content.name, content.group])),
        _category(CAT_GENERAL, bytes(general)),
        _category(CAT_FMMU, bytes([FMMU_USE_OUTPUTS, FMMU_USE_INPUTS,
                                   FMMU_USE_MAILBOX_STATE, 0xFF])),
        _category(CAT_SYNC_MANAGER, b"".join(
            struct.pack("<HHBBBB", sm.start, sm.length, sm.control, 0, 1, sm.use)
            for sm in content.sync_managers)),
    ]
    if content.tx_pdos:
        categories.append(_category(CAT_TXPDO, _pdos(content.tx_pdos, 1)))
    if content.rx_pdos:
        categories.append(_category(CAT_RXPDO, _pdos(content.rx_pdos, 1)))
    image = bytes(words) + b"".join(categories) + struct.pack("<H", CAT_END)
    if len(image) > SII_BYTES:
        raise ValueError(f"the SII of {content.name!r} needs {len(image)} bytes, more than "
                         f"the {SII_BYTES} of the emulated EEPROM")
    return image.ljust(SII_BYTES, b"\xff")

