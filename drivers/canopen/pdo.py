"""PDO configuration by SDO (CiA 301 7.5.2.35-38): a PDO is invalidated (COB-ID bit 31),
its mapping cleared, written entry by entry, its entry count set, its transmission type set
(1: every SYNC) and validated again, the order the standard requires of a device that checks
it. PDOs the master does not use are invalidated, where the drive has them."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

from hil.drivers.canopen.cyclic import SYNC_COUNTER_MAX
from hil.drivers.canopen.errors import DriveError
from hil.drivers.canopen.sdo import SdoChannel
from hil.protocols.cia301 import (
    ABORT_NO_OBJECT,
    ABORT_NO_SUBINDEX,
    CYCLE_PERIOD,
    RPDO_COMM_BASE,
    SYNC_COUNTER_OVERFLOW,
    TPDO_COMM_BASE,
    SdoAbortError,
)
from hil.protocols.cia402 import PDO_NOT_VALID, TPDO_LAYOUTS, PdoMap

EVERY_SYNC = 1  # transmission type: synchronous, every SYNC
# PDOs the master never uses (RPDO2-4), and the TPDOs 1-4 (which it uses depends on the layout)
RPDO_UNUSED = (RPDO_COMM_BASE + 1, RPDO_COMM_BASE + 2, RPDO_COMM_BASE + 3)
TPDO_COMMS = tuple(TPDO_COMM_BASE + i for i in range(4))


def tpdo_maps(sync_echo: tuple[int, int] | None, layout: str = "two") -> tuple[PdoMap, ...]:
    """The TPDOs as the master maps them: the ``layout``'s (:data:`TPDO_LAYOUTS`), each with
    the drive's SYNC counter echo as its last byte when there is one."""
    if layout not in TPDO_LAYOUTS:
        raise ValueError(f"tpdo_layout must be one of {', '.join(TPDO_LAYOUTS)}, got {layout!r}")
    maps = TPDO_LAYOUTS[layout]
    if sync_echo is None:
        return maps
    echo = (*sync_echo, 8)
    echoed = tuple(replace(pdo, entries=(*pdo.entries, echo)) for pdo in maps)
    if any(pdo.size_bytes > 8 for pdo in echoed):
        raise ValueError(f"tpdo_layout {layout!r} fills its 8 bytes: no room for the "
                         "sync_echo byte")
    return echoed


def without_object(maps: Sequence[PdoMap], index: int) -> tuple[PdoMap, ...]:
    """``maps`` with object ``index`` left out of each (an object the drive lacks)."""
    return tuple(replace(pdo, entries=tuple(e for e in pdo.entries if e[0] != index))
                 for pdo in maps)


def unused_pdos(tpdos: Sequence[PdoMap]) -> tuple[int, ...]:
    """The communication objects of the PDOs the master does not use (RPDO2-4 and the TPDOs
    of 1-4 not in ``tpdos``), invalidated where the drive has them."""
    used = {pdo.comm for pdo in tpdos}
    return (*RPDO_UNUSED, *(comm for comm in TPDO_COMMS if comm not in used))


#: how a setting is written: (index, subindex, value, struct format); the master's journal
SettingWriter = Callable[[int, int, int, str], None]


class PdoConfigurator:
    """Writes PDO maps to one node: reads through its SDO client, writes through ``write``
    (the master's, which keeps each value found to put it back; default: the SDO client)."""

    def __init__(self, sdo: SdoChannel, node_id: int, write: SettingWriter | None = None) -> None:
        self.sdo, self.node_id = sdo, node_id
        self.write: SettingWriter = write or (
            lambda index, subindex, value, fmt: sdo.write(index, subindex, value, fmt))

    def map(self, pdo: PdoMap) -> None:
        """``pdo``'s COB-ID, mapping and transmission type, as CiA 301 orders the writes."""
        write = self.write
        comm, mapping, cob_id = pdo.comm, pdo.mapping, pdo.cob_id(self.node_id)
        entries = pdo.mapping_values()
        write(comm, 1, cob_id | PDO_NOT_VALID, "<I")
        write(mapping, 0, 0, "<B")
        for sub, entry in enumerate(entries, start=1):
            write(mapping, sub, entry, "<I")
        write(mapping, 0, len(entries), "<B")
        write(comm, 2, EVERY_SYNC, "<B")
        write(comm, 1, cob_id, "<I")

    def start_sync_counter(self, has_cycle_period: bool, has_counter: bool) -> None:
        """The SYNC counter on (0x1019 = :data:`SYNC_COUNTER_MAX`; CiA 301: it changes only
        while 0x1006 is 0), for ``[master] sync_echo``: a drive without 0x1019 cannot give
        it."""
        if not has_counter:
            raise DriveError(f"drive node {self.node_id} has no 0x1019 (synchronous counter "
                             "overflow value): [master] sync_echo needs the SYNC counter; set "
                             "sync_echo = \"\"")
        if has_cycle_period:
            self.write(CYCLE_PERIOD, 0, 0, "<I")
        self.write(SYNC_COUNTER_OVERFLOW, 0, SYNC_COUNTER_MAX, "<B")

    def disable(self, comm: int) -> None:
        """Invalidate the PDO of communication object ``comm``; a drive without it is fine."""
        try:
            cob = self.sdo.read_int(comm, 1)
            if not cob & PDO_NOT_VALID:
                self.write(comm, 1, cob | PDO_NOT_VALID, "<I")
        except SdoAbortError as exc:
            if exc.code not in (ABORT_NO_OBJECT, ABORT_NO_SUBINDEX):
                raise
