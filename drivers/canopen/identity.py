"""Who a drive is: its identity object 0x1018 (CiA 301: vendor-ID, product code, revision
number, serial number; only the vendor-ID is mandatory), read by SDO.

It decides two things. Whether the drive is hil's own drive emulator, the only drive hil
writes its manufacturer-specific objects to (0x2000-0x5FFF: the time base 0x2005, the
disturbance torque 0x2003): on a vendor's drive the same index is the vendor's object, with
its own meaning. hil's emulator says so in 0x1018:5, a sub-index CiA 301 leaves unused
(:data:`~hil.protocols.cia301.HIL_EMULATOR_SIGNATURE`), also as the twin of a vendor's drive,
whose 0x1018:1..4 are the vendor's. And, with the bus and the node id, which drive a setting
left behind by an earlier run belongs to (:mod:`hil.drivers.canopen.run_settings`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Protocol

from hil.protocols.cia301 import (
    HIL_EMULATOR_SIGNATURE,
    HIL_EMULATOR_SUBINDEX,
    IDENTITY,
    SdoAbortError,
)

#: manufacturer-specific objects (CiA 301's profile area starts at 0x6000)
MANUFACTURER_OBJECTS = range(0x2000, 0x6000)


class SdoReader(Protocol):
    def read_int(self, index: int, subindex: int = 0, fmt: str = "<I",
                 timeout_s: float | None = None) -> int: ...


@dataclass(frozen=True)
class Identity:
    """0x1018 as the drive answers it; None where it has no such sub-index."""

    vendor_id: int | None = None
    product_code: int | None = None
    revision: int | None = None
    serial: int | None = None
    hil_emulator: bool = False  # 0x1018:5 holds hil's emulator's signature

    def as_dict(self) -> dict[str, int | None]:
        """0x1018:1..4 by name."""
        return {key: value for key, value in asdict(self).items() if key != "hil_emulator"}

    def text(self) -> str:
        """``vendor 0xC0FFEE, product 0x11, revision 0x3, serial 0x1267`` (what it has)."""
        names = {"vendor_id": "vendor", "product_code": "product"}
        return ", ".join(f"{names.get(key, key)} 0x{value:X}"
                         for key, value in self.as_dict().items() if value is not None) \
            or "no identity"


def read_identity(sdo: SdoReader) -> Identity:
    """The drive's 0x1018, each sub-index it refuses left out (a DriveError when it does not
    answer at all)."""
    values: dict[str, int] = {}
    for sub, key in enumerate(("vendor_id", "product_code", "revision", "serial"), start=1):
        try:
            values[key] = sdo.read_int(IDENTITY, sub)
        except SdoAbortError:
            continue
    try:
        signed = sdo.read_int(IDENTITY, HIL_EMULATOR_SUBINDEX) == HIL_EMULATOR_SIGNATURE
    except SdoAbortError:
        signed = False
    return Identity(**values, hil_emulator=signed)


def not_hil_emulator(node_id: int, identity: Identity, objects: str) -> str:
    """Why hil writes none of its ``objects`` to node ``node_id``: one clause."""
    return (f"drive node {node_id} is not hil's drive emulator (0x1018: {identity.text()}): "
            f"hil writes its manufacturer objects ({objects}) to its own emulator only, never "
            "to a vendor's drive, where the same index is the vendor's object")
