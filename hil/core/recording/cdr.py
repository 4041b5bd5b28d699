"""Compact binary encoding of flat topics: CDR messages with a ``ros2msg`` schema.

Foxglove (and any ROS 2 tool) decodes ``cdr`` messages described by a ``ros2msg`` schema
without a plug-in, so a high-rate topic can leave JSON without leaving the ecosystem.

The schema is derived from the topic's JSON Schema, field by field in declaration order:

=====================  ==============================================================
JSON Schema            ros2msg type
=====================  ==============================================================
``number``             ``float64``
``integer``            ``int64``
``boolean``            ``bool``
``string``             ``string``
array of the above     ``float64[]`` ... (unbounded sequence)
=====================  ==============================================================

A property may narrow its wire type with the ``x-cdr`` keyword (``"x-cdr": "float32"``,
``"uint16"``...): JSON Schema ignores unknown keywords, so the same schema still describes the
JSON encoding. A missing field is written as 0, false, "" or an empty sequence; fields that
the schema does not name are not written. Only flat objects qualify:
:func:`cdr_compatible` says whether a schema does.

Encoding is little-endian XCDR1 (encapsulation ``00 01 00 00``); alignment is relative to the
first byte after the encapsulation header, as ROS 2 and Foxglove expect.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR_LE

# ros2msg primitive -> (struct code, size = alignment)
PRIMITIVES: dict[str, tuple[str, int]] = {
    "bool": ("?", 1), "byte": ("B", 1), "uint8": ("B", 1), "int8": ("b", 1),
    "int16": ("h", 2), "uint16": ("H", 2), "int32": ("i", 4), "uint32": ("I", 4),
    "int64": ("q", 8), "uint64": ("Q", 8), "float32": ("f", 4), "float64": ("d", 8),
}
_JSON_TO_ROS = {"number": "float64", "integer": "int64", "boolean": "bool", "string": "string"}
_DEFAULTS = {"bool": False, "string": ""}
_ROS_NAME = re.compile(r"[^a-z0-9_]+|_{2,}")


class CdrError(ValueError):
    """A schema or message that the flat CDR encoding cannot express."""


@dataclass(frozen=True)
class Field:
    name: str            # the JSON name (the key of decoded messages)
    type: str            # a key of PRIMITIVES or "string"
    sequence: bool = False

    @property
    def ros_name(self) -> str:
        """ROS 2 allows lower-case field names only: ``current_mA`` is ``current_ma``."""
        return _ROS_NAME.sub("_", self.name.lower()).strip("_") or "field"


def _field_type(name: str, prop: dict[str, Any]) -> Field:
    if prop.get("type") == "array":
        items = prop.get("items", {})
        inner = _field_type(name, items if isinstance(items, dict) else {})
        if inner.sequence:
            raise CdrError(f"field {name!r}: nested arrays have no flat CDR encoding")
        return Field(name, inner.type, sequence=True)
    wire = prop.get("x-cdr") or _JSON_TO_ROS.get(str(prop.get("type")))
    if wire is None or (wire not in PRIMITIVES and wire != "string"):
        raise CdrError(f"field {name!r}: type {prop.get('type')!r} has no flat CDR encoding")
    return Field(name, wire)


def fields_of(schema: dict[str, Any]) -> list[Field]:
    """The CDR fields of a flat JSON Schema object, in declaration order."""
    properties = schema.get("properties")
    if schema.get("type") != "object" or not isinstance(properties, dict) or not properties:
        raise CdrError("only a JSON Schema object with properties has a flat CDR encoding")
    fields = [_field_type(name, prop) for name, prop in properties.items()]
    ros_names = [f.ros_name for f in fields]
    if len(set(ros_names)) != len(ros_names):
        raise CdrError(f"fields {[f.name for f in fields]} collide once lower-cased for ROS 2")
    return fields


def cdr_compatible(schema: dict[str, Any]) -> bool:
    try:
        fields_of(schema)
    except CdrError:
        return False
    return True


def ros2msg_text(fields: list[Field]) -> str:
    """The ``ros2msg`` definition of ``fields``: one ``type name`` line each, with the JSON
    name in a comment where ROS 2's lower-case rule changed it (``current_ma  # current_mA``)."""
    return "".join(
        f"{f.type}{'[]' if f.sequence else ''} {f.ros_name}"
        f"{'  # ' + f.name if f.ros_name != f.name else ''}\n" for f in fields)


def parse_ros2msg(text: str) -> list[Field]:
    """Read back a flat ``ros2msg`` definition written by :func:`ros2msg_text` (a trailing
    comment names the JSON field; constants are not supported)."""
    fields = []
    for raw in text.splitlines():
        line, _, comment = raw.partition("#")
        line = line.strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 2 or "=" in line:
            raise CdrError(f"ros2msg line {line!r}: expected 'type name'")
        kind, name = parts
        sequence = kind.endswith("[]")
        kind = kind.removesuffix("[]")
        if kind not in PRIMITIVES and kind != "string":
            raise CdrError(f"ros2msg field {name!r}: type {kind!r} is not a flat primitive")
        json_name = comment.strip()
        fields.append(Field(json_name if json_name.lower() == name else name, kind, sequence))
    return fields


def _pad(buf: bytearray, align: int) -> None:
    offset = (len(buf) - 4) % align
    if offset:
        buf.extend(b"\x00" * (align - offset))


_ZEROS = tuple(bytes(n) for n in range(8))  # padding
_COUNT = struct.Struct("<I")
STRINGS_KEPT = 64  # distinct strings right after a head whose bytes an encoder keeps
LENGTHS_KEPT = 16  # lengths of a numeric sequence whose ``struct`` its writer keeps


def _put_string(buf: bytearray, value: Any) -> None:
    """A string (None: empty; anything else as ``str`` gives it), null-terminated."""
    data = ("" if value is None else str(value)).encode()
    buf += _ZEROS[-(len(buf) - 4) % 4]
    buf += _COUNT.pack(len(data) + 1)
    buf += data
    buf.append(0)


class CdrEncoder:
    """Encodes dicts to CDR for one fixed list of fields.

    The encapsulation and the leading run of fixed-size fields (their offsets are known in
    advance) are one precompiled ``struct`` with the alignment padding in it, and each
    numeric sequence or string one ``struct`` call (a string right after the head, a servo
    command's path, from the bytes kept for its value): the writer encodes a servo tick's
    topics several times faster than field by field, and the bytes are the same
    (:meth:`encode_by_field`, the plain definition, is what the tests compare it with and
    what names a value that does not fit).
    """

    def __init__(self, fields: list[Field]) -> None:
        self.fields = fields
        fmt, offset, lead = "<4s", 0, 0
        for f in fields:
            if f.sequence or f.type == "string":
                break
            code, size = PRIMITIVES[f.type]
            pad = -offset % size
            fmt += "x" * pad + code
            offset += pad + size
            lead += 1
        self._head = struct.Struct(fmt)
        self._head_types = [(f.type, PRIMITIVES[f.type][0] not in "fd?") for f in fields[:lead]]
        self._lead = lead
        self._tail = [_tail_writer(f) for f in fields[lead:]]
        self._names = [f.name for f in fields]
        # a string right after the head starts at a known offset: its bytes (padding, count,
        # text, NUL) depend on its value alone, and a topic's strings repeat (a path, a mode)
        self._string_at: int | None = offset if lead < len(fields) \
            and fields[lead].type == "string" and not fields[lead].sequence else None
        self._strings: dict[str, bytes] = {}
        self._after_string = self._tail[1:]

    def encode(self, message: dict[str, Any]) -> bytes:
        return self.encode_row(tuple(map(message.get, self._names)))

    def encode_row(self, row: tuple[Any, ...]) -> bytes:
        """A message given as the values of the fields in order (None: left out)."""
        lead = self._lead
        head: Sequence[Any] = row[:lead] if self._tail else row
        try:
            if None in head:  # left out: 0 packs as 0.0 and as false too
                head = [0 if value is None else value for value in head]
            try:  # the values as they are: an integer field given a float is the rare case
                data = self._head.pack(ENCAPSULATION, *head)
            except struct.error:
                data = self._head.pack(ENCAPSULATION, *self._integral(head))
            if not self._tail:
                return data
            if self._string_at is None:
                buf = bytearray(data)
                writers, values = self._tail, row[lead:]
            else:
                text = self._string_bytes(row[lead])
                if not self._after_string:  # the head and one string: no buffer to build
                    return data + text
                buf = bytearray(data)
                buf += text
                writers, values = self._after_string, row[lead + 1:]
            for write, value in zip(writers, values, strict=True):
                write(buf, value)
        except (struct.error, CdrError):  # raises, naming the field
            return self.encode_by_field(dict(zip(self._names, row, strict=True)))
        return bytes(buf)

    def _string_bytes(self, value: Any) -> bytes:
        """The string right after the head as :func:`_put_string` writes it there; the
        bytes of the first :data:`STRINGS_KEPT` distinct ones kept."""
        if type(value) is str:
            kept = self._strings.get(value)
            if kept is not None:
                return kept
        assert self._string_at is not None
        buf = bytearray(4 + self._string_at)
        _put_string(buf, value)
        data = bytes(buf[4 + self._string_at:])
        if type(value) is str and len(self._strings) < STRINGS_KEPT:
            self._strings[value] = data
        return data

    def _integral(self, head: Sequence[Any]) -> list[Any]:
        """The head's values with integer fields as ``int`` (``3.0`` for a ``uint16``)."""
        return [int(value) if integral else value
                for (_, integral), value in zip(self._head_types, head, strict=False)]

    def encode_by_field(self, message: dict[str, Any]) -> bytes:
        """The same bytes as :meth:`encode`, written field by field and item by item."""
        buf = bytearray(ENCAPSULATION)
        for f in self.fields:
            self._put_field(buf, f, message.get(f.name))
        return bytes(buf)

    @staticmethod
    def _put_field(buf: bytearray, f: Field, value: Any) -> None:
        """One field, a sequence item by item."""
        if not f.sequence:
            CdrEncoder._put(buf, f, value)
            return
        items = [] if value is None else list(value)
        _pad(buf, 4)
        buf.extend(struct.pack("<I", len(items)))
        for item in items:
            CdrEncoder._put(buf, f, item)

    @staticmethod
    def _put(buf: bytearray, f: Field, value: Any) -> None:
        if f.type == "string":
            _put_string(buf, value)
            return
        code, size = PRIMITIVES[f.type]
        if value is None:
            value = _DEFAULTS.get(f.type, 0)
        elif code not in "fd?":
            value = int(value)
        _pad(buf, size)
        try:
            buf.extend(struct.pack("<" + code, value))
        except struct.error as exc:
            raise CdrError(f"field {f.name!r}: {value!r} does not fit {f.type}") from exc


def _tail_writer(f: Field) -> Callable[[bytearray, Any], None]:
    """How :class:`CdrEncoder` writes a field after the fixed head: a numeric sequence as
    its count and items in one ``struct`` call, anything else as :meth:`CdrEncoder._put_field`
    writes it."""
    if not f.sequence or f.type == "string":
        if f.type == "string" and not f.sequence:
            return _put_string
        return lambda buf, value: CdrEncoder._put_field(buf, f, value)
    code, size = PRIMITIVES[f.type]
    integral = code not in "fd?"
    # items of 4 bytes or less follow the count without padding: count and items in one call,
    # a struct per length kept (a topic's sequences keep theirs: a horizon)
    counted_format = "<I{}" + code if size <= 4 else None
    counted: dict[int, struct.Struct] = {}
    item_format = "<{}" + code

    def write(buf: bytearray, value: Any) -> None:
        if type(value) is not list:
            value = [] if value is None else (
                value.tolist() if hasattr(value, "tolist") else list(value))  # numpy: one call
        if integral:
            value = [int(item) for item in value]
        buf += _ZEROS[-(len(buf) - 4) % 4]
        if counted_format is not None:
            items = len(value)
            packer = counted.get(items)
            if packer is None:
                packer = struct.Struct(counted_format.format(items))
                if len(counted) < LENGTHS_KEPT:
                    counted[items] = packer
            buf += packer.pack(items, *value)
            return
        buf += _COUNT.pack(len(value))
        if value:
            buf += _ZEROS[-(len(buf) - 4) % size]
            buf += struct.pack(item_format.format(len(value)), *value)

    return write


class CdrDecoder:
    """Decodes CDR payloads of one fixed list of fields back to dicts."""

    def __init__(self, fields: list[Field]) -> None:
        self.fields = fields

    def decode(self, payload: bytes) -> dict[str, Any]:
        if payload[:2] != ENCAPSULATION[:2]:
            raise CdrError("not little-endian CDR (encapsulation header)")
        view = memoryview(payload)
        pos = 4
        out: dict[str, Any] = {}
        for f in self.fields:
            if f.sequence:
                pos = _align(pos, 4)
                (count,) = struct.unpack_from("<I", view, pos)
                pos += 4
                items = []
                for _ in range(count):
                    item, pos = self._get(view, pos, f)
                    items.append(item)
                out[f.name] = items
            else:
                out[f.name], pos = self._get(view, pos, f)
        return out

    @staticmethod
    def _get(view: memoryview, pos: int, f: Field) -> tuple[Any, int]:
        if f.type == "string":
            pos = _align(pos, 4)
            (length,) = struct.unpack_from("<I", view, pos)
            start = pos + 4
            return bytes(view[start:start + max(length - 1, 0)]).decode(), start + length
        code, size = PRIMITIVES[f.type]
        pos = _align(pos, size)
        return struct.unpack_from("<" + code, view, pos)[0], pos + size


def _align(pos: int, align: int) -> int:
    offset = (pos - 4) % align
    return pos + (align - offset if offset else 0)
