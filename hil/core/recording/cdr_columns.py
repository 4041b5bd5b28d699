"""A CDR topic decoded field by field over all its messages at once, with numpy.

A flat CDR message (:mod:`hil.core.recording.cdr`) opens with its fixed-size fields at the same
offsets in every message: they are one numpy structured dtype over the topic's message bytes
(:attr:`CdrColumns.head`), read in one gather. A string or a sequence moves what follows it by
its own length, message by message: the offsets of the fields after it are vectors, one offset
per message, computed for all messages at once, and each field is read where it lies.

:meth:`CdrColumns.lay_out` places every field of every message and checks that each message
holds all of them as :class:`~hil.core.recording.cdr.CdrDecoder` would read them; it gives
None when one does not (too short, a length past its end, a string that is not UTF-8, a
sequence of strings), and the caller decodes message by message, where such a message reads
as undecodable. Fields are decoded when asked for (:meth:`Layout.column`,
:meth:`Layout.values`), each value as :class:`~hil.core.recording.cdr.CdrDecoder` gives it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import islice
from typing import Any

import numpy as np

from hil.core.recording.cdr import PRIMITIVES, Field
from hil.core.recording.chunk_messages import read_at

_U32 = np.dtype("<u4")
_ENCAPSULATION = np.dtype("<u2")
_CDR_LE = 0x0100  # the encapsulation's first two bytes, 00 01, read as little-endian uint16
_INT64_MAX = np.iinfo(np.int64).max


def wire_dtype(kind: str) -> np.dtype:
    """The numpy type of a primitive on the wire (bool as its byte: any non-zero is true)."""
    code = PRIMITIVES[kind][0]
    return np.dtype("u1" if code == "?" else "<" + code)


def as_array(values: Sequence[Any]) -> np.ndarray:
    """Values of one field, one per message, as one array: numpy's own choice of type, a list
    per message 2-D when their lengths agree, an object array of them when they do not."""
    try:
        return np.array(values)
    except ValueError:  # ragged lists
        array = np.empty(len(values), dtype=object)
        array[:] = values
        return array


@dataclass(frozen=True)
class _Fixed:
    """A primitive at offset ``at`` of every message (an int: the same in all)."""

    kind: str
    at: int | np.ndarray


@dataclass(frozen=True)
class _Sequence:
    """A numeric sequence: ``count`` items from offset ``first`` of each message."""

    kind: str
    first: np.ndarray
    count: np.ndarray


@dataclass(frozen=True)
class _Strings:
    """A string field, decoded when the messages were laid out (to know each one reads)."""

    values: list[str]


class CdrColumns:
    """Column decoding for one list of fields (a topic's ``ros2msg`` schema)."""

    def __init__(self, fields: list[Field]) -> None:
        self.fields = fields
        self.supported = not any(f.sequence and f.type == "string" for f in fields)
        offsets, pos = {}, 4
        for f in fields:  # the leading fixed-size fields: the same offsets in every message
            if f.sequence or f.type == "string":
                break
            pos = _align(pos, PRIMITIVES[f.type][1])
            offsets[f.name] = pos
            pos += PRIMITIVES[f.type][1]
        #: the structured dtype of the leading fixed-size fields, over each message's bytes
        self.head = np.dtype({"names": list(offsets),
                              "formats": [wire_dtype(f.type) for f in fields[:len(offsets)]],
                              "offsets": list(offsets.values()), "itemsize": pos})

    def lay_out(self, data: np.ndarray, starts: np.ndarray, sizes: np.ndarray
                ) -> Layout | None:
        """Where each field of each message lies: the message ``k`` is ``data[starts[k]:
        starts[k] + sizes[k]]`` (``data``: uint8). None when a message does not hold its
        fields as the per-message decoder reads them, or the schema has a sequence of
        strings."""
        if not self.supported:
            return None
        smallest = int(sizes.min()) if sizes.size else 0
        if starts.size and (smallest < 2 or
                            (read_at(data, starts, _ENCAPSULATION) != _CDR_LE).any()):
            return None

        def holds(end: int | np.ndarray) -> bool:
            return end <= smallest if isinstance(end, int) else bool((end <= sizes).all())

        places: dict[str, _Fixed | _Sequence | _Strings] = {}
        pos: int | np.ndarray = 4
        for f in self.fields:
            if f.type == "string":
                pos = _align(pos, 4)
                if not holds(pos + 4):
                    return None
                length = read_at(data, starts + pos, _U32).astype(np.int64)
                end = pos + 4 + length
                values = _strings(data, starts + pos + 4, length) if holds(end) else None
                if values is None:
                    return None
                places[f.name], pos = _Strings(values), end
            elif f.sequence:
                size = PRIMITIVES[f.type][1]
                pos = _align(pos, 4)
                if not holds(pos + 4):
                    return None
                count = read_at(data, starts + pos, _U32).astype(np.int64)
                first = np.where(count > 0, _align(pos + 4, size), pos + 4)
                pos = first + count * size
                if not holds(pos):
                    return None
                places[f.name] = _Sequence(f.type, starts + first, count)
            else:
                pos = _align(pos, PRIMITIVES[f.type][1])
                places[f.name] = _Fixed(f.type, pos if isinstance(pos, int) else starts + pos)
                pos = pos + PRIMITIVES[f.type][1]
                if not holds(pos):
                    return None
        return Layout(self, data, starts, places)


class Layout:
    """Every field of a topic's messages placed; each decoded when first asked for."""

    def __init__(self, columns: CdrColumns, data: np.ndarray, starts: np.ndarray,
                 places: dict[str, _Fixed | _Sequence | _Strings]) -> None:
        self.fields = columns.fields
        self.names = [f.name for f in columns.fields]
        self.count = int(starts.size)
        self._head_dtype = columns.head
        self._data, self._starts, self._places = data, starts, places
        self._head: np.ndarray | None = None

    def column(self, name: str) -> np.ndarray:
        """The field as one array, as ``SessionData.arrays`` gives it: numbers as float64 or
        int64, booleans as bool, strings as text, sequences 2-D (or objects when their
        lengths differ)."""
        place = self._places[name]
        if isinstance(place, _Fixed):
            column = _typed(self._wire(name, place), place.kind)
        elif isinstance(place, _Sequence) and place.count.size and place.count[0] > 0 and \
                (place.count == place.count[0]).all():  # 2-D (empty lists: numpy's float64)
            items = self._items(place)
            column = _typed(items, place.kind)
            if column is not None:
                column = column.reshape(self.count, int(place.count[0]))
        else:
            column = None
        return as_array(self.values(name)) if column is None else column

    def values(self, name: str) -> list[Any]:
        """The field of each message as Python values, as the per-message decoder reads it."""
        place = self._places[name]
        if isinstance(place, _Strings):
            return place.values
        if isinstance(place, _Fixed):
            return _python(self._wire(name, place), place.kind)
        flat = _python(self._items(place), place.kind)
        if place.count.size and (place.count == place.count[0]).all():
            width = int(place.count[0])
            return [flat[k:k + width] for k in range(0, len(flat), width)] if width else \
                [[] for _ in range(self.count)]
        items = iter(flat)
        return [list(islice(items, n)) for n in place.count.tolist()]

    def messages(self) -> list[dict[str, Any]]:
        """Every message as the dict the per-message decoder gives."""
        columns = [self.values(name) for name in self.names]
        if not columns:
            return [{} for _ in range(self.count)]
        return [dict(zip(self.names, row, strict=True)) for row in zip(*columns, strict=True)]

    def _wire(self, name: str, place: _Fixed) -> np.ndarray:
        """A fixed field's values in their wire type."""
        if isinstance(place.at, int):  # in the head: one gather of every message's head
            if self._head is None:
                rows = np.lib.stride_tricks.sliding_window_view(
                    self._data, self._head_dtype.itemsize)[self._starts]
                self._head = rows.view(self._head_dtype)[:, 0]
            return np.asarray(self._head[name])
        return read_at(self._data, place.at, wire_dtype(place.kind))

    def _items(self, place: _Sequence) -> np.ndarray:
        """Every item of a sequence field, message after message, in its wire type."""
        dtype = wire_dtype(place.kind)
        total = int(place.count.sum())
        before = np.cumsum(place.count) - place.count
        at = np.repeat(place.first - before * dtype.itemsize, place.count) + \
            np.arange(total, dtype=np.int64) * dtype.itemsize
        return read_at(self._data, at, dtype)


def _align(pos: Any, align: int) -> Any:
    """``pos`` (an offset or a vector of them) aligned as CDR does, from the first byte after
    the encapsulation."""
    return pos + (-(pos - 4)) % align


def _strings(data: np.ndarray, first: np.ndarray, length: np.ndarray) -> list[str] | None:
    """The strings of ``length`` bytes (their NUL included) from ``first``; None when one is
    not UTF-8. When each ends in its NUL and holds no other, all are decoded in one go."""
    if length.size == 0:
        return []
    if (length >= 1).all():
        before = np.cumsum(length) - length
        joined = data[np.repeat(first - before, length) +
                      np.arange(int(length.sum()), dtype=np.int64)].tobytes()
        if joined.count(0) == length.size and (data[first + length - 1] == 0).all():
            try:
                return joined.decode().split("\x00")[:-1]
            except UnicodeDecodeError:
                return None
    try:
        return [data[a:a + max(n - 1, 0)].tobytes().decode()
                for a, n in zip(first.tolist(), length.tolist(), strict=True)]
    except UnicodeDecodeError:
        return None


def _typed(wire: np.ndarray, kind: str) -> np.ndarray | None:
    """Wire values as ``np.array`` types the same values given as Python numbers: float64,
    int64, bool; None for a uint64 beyond int64 (numpy's choice then depends on them all)."""
    if kind == "bool":
        return wire != 0
    if wire.dtype.kind == "f":
        with np.errstate(invalid="ignore"):  # a signalling NaN (damaged bytes) stays a NaN
            return wire.astype(np.float64)
    if wire.dtype == np.uint64 and wire.size and int(wire.max()) > _INT64_MAX:
        return None
    return wire.astype(np.int64)


def _python(wire: np.ndarray, kind: str) -> list[Any]:
    """Wire values as the Python numbers ``struct`` gives (a bool for any non-zero byte)."""
    return (wire != 0).tolist() if kind == "bool" else wire.tolist()
