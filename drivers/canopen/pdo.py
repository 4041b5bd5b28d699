"""PDO configuration by SDO (CiA 301 7.5.2.35-38): a PDO is invalidated (COB-ID bit 31),
its mapping cleared, written entry by entry, its entry count set, its transmission type set
(1: every SYNC) and validated again, the order the standard requires of a device that checks
it. PDOs the master does not use are invalidated, where the drive has them."""

from __future__ import annotations

from hil.drivers.canopen.sdo import SdoClient
from hil.protocols.cia301 import ABORT_NO_OBJECT, ABORT_NO_SUBINDEX, SdoAbortError
from hil.protocols.cia402 import PDO_NOT_VALID, PdoMap

EVERY_SYNC = 1  # transmission type: synchronous, every SYNC


class PdoConfigurator:
    """Writes PDO maps to one node through its SDO client."""

    def __init__(self, sdo: SdoClient, node_id: int) -> None:
        self.sdo, self.node_id = sdo, node_id

    def map(self, pdo: PdoMap) -> None:
        """``pdo``'s COB-ID, mapping and transmission type, as CiA 301 orders the writes."""
        write = self.sdo.write
        comm, mapping, cob_id = pdo.comm, pdo.mapping, pdo.cob_id(self.node_id)
        entries = pdo.mapping_values()
        write(comm, 1, cob_id | PDO_NOT_VALID)
        write(mapping, 0, 0, "<B")
        for sub, entry in enumerate(entries, start=1):
            write(mapping, sub, entry)
        write(mapping, 0, len(entries), "<B")
        write(comm, 2, EVERY_SYNC, "<B")
        write(comm, 1, cob_id)

    def disable(self, comm: int) -> None:
        """Invalidate the PDO of communication object ``comm``; a drive without it is fine."""
        try:
            cob = self.sdo.read_int(comm, 1)
            if not cob & PDO_NOT_VALID:
                self.sdo.write(comm, 1, cob | PDO_NOT_VALID)
        except SdoAbortError as exc:
            if exc.code not in (ABORT_NO_OBJECT, ABORT_NO_SUBINDEX):
                raise
