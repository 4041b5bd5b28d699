"""The emulated drive's PDOs (CiA 301 7.2.2): each PDO compiled from its communication and
mapping objects whenever one of them changes, the rules for changing them (a valid PDO's
COB-ID and mapping are frozen; a mapping entry must name a mappable object of its size, at
most 64 bits in all), received RPDO data checked for length and held for the next SYNC, and
the TPDO frames: on SYNC (transmission types 1..240 every that many SYNCs, 0 on the SYNC after
its data changed) or on an event (254, 255: when its data changed, at most once per inhibit
time, sub 3 in 100 us, and at least every event timer, sub 5 in ms, when it is set). The
PDOs are those the dictionary has: every communication object 0x1400.. (RPDO) and 0x1800..
(TPDO) with its mapping object 0x200 above it, and every mapping object 0x1600.. / 0x1A00..
without one (an EtherCAT drive's PDOs, from its ESI: no CAN frame carries them, so they are
never valid on CAN and are not held to a frame's 64 bits; the EtherCAT slave assigns them to
its SyncManagers, :mod:`hil.emulators.ethercat.assignment`)."""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from operator import itemgetter
from typing import Any

from canopen.objectdictionary import ODVariable

from hil.emulators.drive.objects import Key, ObjectStore
from hil.protocols.can_frames import Frame
from hil.protocols.cia301 import (
    ABORT_CANNOT_MAP,
    ABORT_NO_OBJECT,
    ABORT_PDO_TOO_LONG,
    ABORT_UNSUPPORTED,
    ABORT_VALUE,
    ABORT_VALUE_HIGH,
    EMCY_PDO_LENGTH,
    EMCY_PDO_TOO_LONG,
    RPDO_COMM_BASE,
    TPDO_COMM_BASE,
    SdoAbortError,
)
from hil.protocols.cia402 import PDO_NOT_VALID

EXTENDED_ID = 0x2000_0000  # COB-ID bit 29: a 29-bit identifier (not supported here)
MAX_PDO_BITS = 64
LAST_SYNCHRONOUS_TYPE = 240
EVENT_TYPES = (254, 255)  # event-driven TPDOs (manufacturer-specific, profile-specific)
INHIBIT, EVENT_TIMER = 3, 5  # the TPDO communication object's sub-indices
PDOS_PER_DIRECTION = 512  # CiA 301: communication objects 0x1400..0x15FF, 0x1800..0x19FF
MAPPING_OFFSET = 0x200    # a PDO's mapping object is 0x200 above its communication object


@dataclass
class Pdo:
    """Compiled view of one PDO (rebuilt whenever its communication or mapping object
    changes)."""

    comm: int | None  # None: a mapping object alone (EtherCAT's PDOs)
    mapping: int
    transmit: bool
    cob_id: int = 0
    valid: bool = False
    trans_type: int = 1
    keys: tuple[Key, ...] = ()
    layout: struct.Struct = field(default_factory=lambda: struct.Struct("<"))
    #: the values of ``keys`` from a value store, as a tuple
    read: Callable[[dict[Key, Any]], tuple[Any, ...]] = field(default=lambda _values: ())
    counter: int = 0
    length_error: bool = False
    inhibit_ns: int = 0       # event-driven TPDO: at most one per this
    event_ns: int = 0         # event-driven TPDO: at least one per this (0: on change only)
    last_data: bytes | None = None  # a TPDO's data when it was last sent
    last_ns: int = 0


def reader(keys: tuple[Key, ...]) -> Callable[[dict[Key, Any]], tuple[Any, ...]]:
    """What reads the values of ``keys`` from a value store, as a tuple, in one call."""
    if len(keys) == 1:
        key = keys[0]
        return lambda values: (values[key],)
    return itemgetter(*keys) if keys else lambda _values: ()


def pdo_struct(var: ODVariable) -> struct.Struct:
    """The wire format of a variable in a PDO (fixed-size types only)."""
    data_type = var.data_type
    if data_type is None or data_type not in var.STRUCT_TYPES:
        raise SdoAbortError(ABORT_CANNOT_MAP)
    layout: struct.Struct = var.STRUCT_TYPES[data_type]
    return layout


class PdoTable:
    """The drive's RPDOs and TPDOs over its ``objects``."""

    def __init__(self, objects: ObjectStore) -> None:
        self.objects = objects
        od = objects.od
        self.pdos = [Pdo(comm if comm in od else None, comm + MAPPING_OFFSET, transmit)
                     for base, transmit in ((RPDO_COMM_BASE, False), (TPDO_COMM_BASE, True))
                     for comm in range(base, base + PDOS_PER_DIRECTION)
                     if comm + MAPPING_OFFSET in od]
        self.by_object: dict[int, Pdo] = {}
        for pdo in self.pdos:
            if pdo.comm is not None:
                self.by_object[pdo.comm] = pdo
            self.by_object[pdo.mapping] = pdo
        self.pending: dict[int, bytes] = {}  # RPDO data held for the next SYNC
        # the cyclic path's views, rebuilt whenever a PDO is compiled
        #: the valid RPDOs by COB-ID (the first one wins): a new dict whenever one is compiled
        self.receivers: dict[int, Pdo] = {}
        self._transmitters: list[Pdo] = []    # the valid synchronous TPDOs, in order
        self.on_event: list[Pdo] = []         # the valid event-driven TPDOs, in order

    def compile_all(self) -> None:
        for pdo in self.pdos:
            self.compile(pdo)

    def compile(self, pdo: Pdo) -> None:
        values = self.objects.values
        if pdo.comm is not None:
            cob = values[(pdo.comm, 1)]
            pdo.cob_id = cob & 0x7FF
            pdo.valid = not cob & PDO_NOT_VALID
            pdo.trans_type = values[(pdo.comm, 2)]
            pdo.inhibit_ns = (values.get((pdo.comm, INHIBIT)) or 0) * 100_000
            pdo.event_ns = (values.get((pdo.comm, EVENT_TIMER)) or 0) * 1_000_000
        keys, fmt = [], "<"
        for sub in range(1, values[(pdo.mapping, 0)] + 1):
            entry = values[(pdo.mapping, sub)]
            index, subindex = entry >> 16, (entry >> 8) & 0xFF
            var = self.objects.find(index, subindex)
            keys.append((index, subindex))
            fmt += pdo_struct(var).format.lstrip("<")
        pdo.keys, pdo.layout = tuple(keys), struct.Struct(fmt)
        pdo.read = reader(pdo.keys)
        self.receivers = {}
        for each in self.pdos:
            if not each.transmit and each.valid:
                self.receivers.setdefault(each.cob_id, each)
        self._transmitters = [each for each in self.pdos if each.transmit and each.valid
                              and each.trans_type <= LAST_SYNCHRONOUS_TYPE]
        self.on_event = [each for each in self.pdos if each.transmit and each.valid
                          and each.trans_type in EVENT_TYPES]

    # -- writes to the PDO objects (SDO) ----------------------------------------------------
    def write(self, pdo: Pdo, index: int, subindex: int, value: int) -> None:
        """One write to ``pdo``'s communication or mapping object, under CiA 301's rules."""
        values = self.objects.values
        key = (index, subindex)
        if index == pdo.comm:
            if subindex == 1:
                if value & EXTENDED_ID or value & 0x7FF == 0:
                    raise SdoAbortError(ABORT_VALUE)  # 29-bit ids are not supported here
                old = values[key]
                both_valid = not (old | value) & PDO_NOT_VALID
                if both_valid and (old & 0x7FF) != (value & 0x7FF):
                    raise SdoAbortError(ABORT_VALUE)  # invalidate before changing the id
            elif subindex == 2:
                allowed = [*range(LAST_SYNCHRONOUS_TYPE + 1), *EVENT_TYPES]
                if value not in allowed:
                    raise SdoAbortError(ABORT_VALUE)
            values[key] = value
        else:
            if pdo.comm is not None and not values[(pdo.comm, 1)] & PDO_NOT_VALID:
                raise SdoAbortError(ABORT_UNSUPPORTED)  # mapping of a valid PDO is frozen
            if subindex == 0:
                if any((index, s) not in values for s in range(1, value + 1)):
                    raise SdoAbortError(ABORT_VALUE_HIGH)  # more entries than it has
                self.check_mapping(pdo, [values[(index, s)] for s in range(1, value + 1)])
            elif values[(index, 0)] != 0:
                raise SdoAbortError(ABORT_UNSUPPORTED)  # disable the mapping first
            elif value:  # 0 clears an unused entry
                self.check_mapping(pdo, [value])
            values[key] = value
        self.compile(pdo)

    def check_mapping(self, pdo: Pdo, entries: list[int]) -> None:
        bits = 0
        for entry in entries:
            index, subindex, size = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
            try:
                var = self.objects.find(index, subindex)
            except SdoAbortError:
                raise SdoAbortError(ABORT_NO_OBJECT) from None
            usable = var.readable if pdo.transmit else var.writable
            emulated = (index, subindex) not in (
                self.objects.no_read if pdo.transmit else self.objects.no_write)
            if not var.pdo_mappable or not usable or not emulated or size != len(var):
                raise SdoAbortError(ABORT_CANNOT_MAP)
            bits += size
        if pdo.comm is not None and bits > MAX_PDO_BITS:  # a CAN frame's
            raise SdoAbortError(ABORT_PDO_TOO_LONG)

    # -- the cyclic path ------------------------------------------------------------------
    def receive(self, pdo: Pdo, data: bytes) -> tuple[bytes | None, int]:
        """RPDO data: (the data to apply now, or None when it is held for the next SYNC or
        refused; the EMCY code of a length error, reported once per episode, or 0)."""
        size = pdo.layout.size
        emcy = 0
        if len(data) < size:
            if not pdo.length_error:
                pdo.length_error = True
                emcy = EMCY_PDO_LENGTH
            return None, emcy
        if len(data) > size and not pdo.length_error:
            pdo.length_error = True
            emcy = EMCY_PDO_TOO_LONG
        elif len(data) == size:
            pdo.length_error = False
        if pdo.trans_type <= LAST_SYNCHRONOUS_TYPE:
            self.pending[pdo.mapping] = data[:size]  # latched on the next SYNC
            return None, emcy
        return data[:size], emcy

    def latched(self) -> list[tuple[Pdo, bytes]]:
        """The RPDO data held for this SYNC, in PDO order (then forgotten)."""
        pending, by_object = self.pending, self.by_object
        if len(pending) == 1:  # the usual one: no order to sort out
            mapping, data = pending.popitem()
            return [(by_object[mapping], data)]
        out = [(by_object[mapping], pending[mapping]) for mapping in sorted(pending)]
        pending.clear()
        return out

    def restart(self) -> None:
        """Entering OPERATIONAL: nothing held, the transmission counters from zero."""
        self.pending.clear()
        for pdo in self.pdos:
            pdo.counter = 0
            pdo.last_data = None

    def tpdo_frames(self) -> list[Frame]:
        """The TPDOs this SYNC sends (each valid one whose transmission type is due)."""
        frames = []
        values = self.objects.values
        for pdo in self._transmitters:
            if pdo.trans_type == 0:  # acyclic: on the SYNC after its data changed
                data = pdo.layout.pack(*pdo.read(values))
                if data != pdo.last_data:
                    pdo.last_data = data
                    frames.append((pdo.cob_id, data))
                continue
            pdo.counter += 1
            if pdo.counter >= pdo.trans_type:
                pdo.counter = 0
                frames.append((pdo.cob_id, pdo.layout.pack(*pdo.read(values))))
        return frames

    def event_frames(self, now_ns: int) -> list[Frame]:
        """The event-driven TPDOs due at ``now_ns``: their data changed (and the inhibit time
        passed since the last one), or the event timer ran out."""
        frames = []
        for pdo in self.on_event:
            data = self.data(pdo)
            since = now_ns - pdo.last_ns
            changed = data != pdo.last_data and (pdo.last_data is None or
                                                 since >= pdo.inhibit_ns)
            if changed or (pdo.event_ns and since >= pdo.event_ns):
                pdo.last_data, pdo.last_ns = data, now_ns
                frames.append((pdo.cob_id, data))
        return frames

    def data(self, pdo: Pdo) -> bytes:
        """``pdo``'s data now: its mapped objects' values, packed."""
        return pdo.layout.pack(*pdo.read(self.objects.values))
