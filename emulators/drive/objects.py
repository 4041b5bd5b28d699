"""The emulated drive's objects: its dictionary (types, access, limits, defaults) and the live
values, with the checks an SDO access gets (CiA 301 abort codes).

A twin built from a drive's EDS (:mod:`hil.emulators.drive.twin`) also has objects the node
keeps without showing them (``hidden``: hil's objects the EDS lacks, which SDO says do not
exist), and objects it shows but cannot emulate: ``no_read`` (a read is refused with 0x08000024
no data available: the twin has no value that would mean what the drive's means) and
``no_write`` (a write is refused with 0x08000020 data cannot be stored to the application: the
twin has nothing that would do what writing it does on the drive)."""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable
from typing import Any

from canopen.objectdictionary import ObjectDictionary, ODVariable
from canopen.objectdictionary.datatypes import VISIBLE_STRING

from hil.emulators.drive.od import iter_variables
from hil.protocols.cia301 import (
    ABORT_CANNOT_STORE,
    ABORT_LENGTH,
    ABORT_NO_DATA,
    ABORT_NO_OBJECT,
    ABORT_NO_SUBINDEX,
    ABORT_READ_ONLY,
    ABORT_VALUE_HIGH,
    ABORT_VALUE_LOW,
    ABORT_WRITE_ONLY,
    SdoAbortError,
)

Key = tuple[int, int]


class ObjectStore:
    """The dictionary ``od`` and the live ``values`` by ``(index, subindex)``; ``hidden``,
    ``no_read`` and ``no_write`` as the module says."""

    def __init__(self, od: ObjectDictionary, *, hidden: Iterable[ODVariable] = (),
                 no_read: Iterable[Key] = (), no_write: Iterable[Key] = ()) -> None:
        self.od = od
        self.hidden = tuple(hidden)
        self.no_read, self.no_write = frozenset(no_read), frozenset(no_write)
        self.values: dict[Key, Any] = {}

    def reset(self, where: Callable[[ODVariable], bool] = lambda var: True) -> None:
        """The objects ``where`` selects back to their defaults."""
        for var in (*iter_variables(self.od), *self.hidden):
            if where(var):
                self.values[(var.index, var.subindex)] = var.default

    def find(self, index: int, subindex: int) -> ODVariable:
        """The object, or an SdoAbortError (no object, no sub-index)."""
        if index not in self.od:
            raise SdoAbortError(ABORT_NO_OBJECT)
        obj = self.od[index]
        if isinstance(obj, ODVariable):
            if subindex != 0:
                raise SdoAbortError(ABORT_NO_SUBINDEX)
            return obj
        if subindex not in obj.subindices:
            raise SdoAbortError(ABORT_NO_SUBINDEX)
        var: ODVariable = obj.subindices[subindex]
        return var

    def read(self, index: int, subindex: int) -> bytes:
        """An SDO upload: the value's bytes. A value its type cannot hold (a twin's file gave
        a string that is not ASCII, a number out of its range) is no data to give."""
        var = self.find(index, subindex)
        if not var.readable:
            raise SdoAbortError(ABORT_WRITE_ONLY)
        if (index, subindex) in self.no_read:
            raise SdoAbortError(ABORT_NO_DATA)
        try:
            data: bytes = var.encode_raw(self.values[(index, subindex)])
        except (ValueError, TypeError, struct.error):  # UnicodeEncodeError is a ValueError
            raise SdoAbortError(ABORT_NO_DATA) from None
        return data

    def decode_download(self, index: int, subindex: int, data: bytes) -> int:
        """An SDO download's value, checked for access, size, type and range (not stored:
        what writing means is the node's)."""
        var = self.find(index, subindex)
        if not var.writable:
            raise SdoAbortError(ABORT_READ_ONLY)
        if (index, subindex) in self.no_write or var.data_type == VISIBLE_STRING:
            raise SdoAbortError(ABORT_CANNOT_STORE)
        if len(data) * 8 != len(var):
            raise SdoAbortError(ABORT_LENGTH)
        value = var.decode_raw(bytes(data))
        if not isinstance(value, int):  # the emulator's writable objects are integers
            raise SdoAbortError(ABORT_CANNOT_STORE)
        if var.min is not None and value < var.min:
            raise SdoAbortError(ABORT_VALUE_LOW)
        if var.max is not None and value > var.max:
            raise SdoAbortError(ABORT_VALUE_HIGH)
        return value
