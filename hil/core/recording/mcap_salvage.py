"""What can still be read of a damaged MCAP file: the records of a chunk up to its damage, and
where the records go on after bytes that are no record.

:func:`salvage_chunk` takes the intact prefix of a chunk record (as the chunk's check record
says it, :mod:`hil.core.recording.chunk_check`, or as a file cut short leaves it), decompresses
its zstd stream as far as it goes and parses the complete records in what came out.
:func:`restart_after` finds the next place a record starts after damage: the next chunk's check
record or the next chunk (found by its fixed layout), or an offset the file's summary indexes,
when its summary is intact.
"""

from __future__ import annotations

import io
import mmap
import struct
import zlib
from collections.abc import Callable
from typing import Any

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.records import Channel, Message, Schema

from hil.core.recording.chunk_check import OPCODE as CHECK_OPCODE
from hil.core.recording.chunk_check import TAG as CHECK_TAG
from hil.core.recording.chunk_check import ChunkCheck

Buffer = bytes | mmap.mmap
HEAD = struct.Struct("<BQ")
CHUNK_OPCODE = 0x06
# a chunk record up to its compression: opcode, length, start, end, uncompressed size and CRC
_CHUNK_FIELDS = struct.Struct("<BQQQQI")
_ZSTD_CHUNK = b"\x04\x00\x00\x00zstd"  # its compression, a string: length, then the name
_FOOTER = struct.Struct("<BQQQI")      # opcode, length, summary start, offsets start, CRC
MAGIC_BYTES = 8
INFLATE_STEP = 16 * 1024

_IN_CHUNK: dict[int, Callable[[ReadDataStream, int], Any]] = {
    0x03: lambda s, n: Schema.read(s),
    0x04: lambda s, n: Channel.read(s),
    0x05: lambda s, n: Message.read(s, n),
}


def salvage_chunk(prefix: bytes) -> tuple[list[Any], int]:
    """The schemas, channels and messages of a chunk record whose first ``len(prefix)``
    bytes are the writer's: its stream decompressed as far as it goes, every complete record
    in what came out; and how many bytes of the chunk's content they are."""
    head = _CHUNK_FIELDS.size
    if len(prefix) < head + 4:
        return [], 0
    uncompressed = _CHUNK_FIELDS.unpack_from(prefix)[4]
    (name_length,) = struct.unpack_from("<I", prefix, head)
    data_start = head + 4 + name_length + 8
    compression = prefix[head + 4:head + 4 + name_length]
    data = prefix[data_start:]
    if compression == b"zstd":
        content = _inflate(data, uncompressed)
    elif compression == b"":
        content = data[:uncompressed]
    else:  # lz4, or a name the damage left: nothing to decompress
        return [], 0
    return _records(content)


def _inflate(data: bytes, limit: int) -> bytes:
    """As much of the zstd stream ``data`` as decodes, ``limit`` bytes at most."""
    stream = zstandard.ZstdDecompressor().decompressobj()
    out = bytearray()
    try:
        for at in range(0, len(data), INFLATE_STEP):
            out += stream.decompress(data[at:at + INFLATE_STEP])
            if len(out) >= limit:
                break
    except zstandard.ZstdError:
        pass  # what came out before the error is what the blocks before it held
    return bytes(out[:limit])


def _records(content: bytes) -> tuple[list[Any], int]:
    """Every complete, readable record at the start of a chunk's content, and their bytes."""
    records = []
    pos = 0
    while pos + HEAD.size <= len(content):
        opcode, length = HEAD.unpack_from(content, pos)
        end = pos + HEAD.size + length
        if end > len(content):
            break
        read = _IN_CHUNK.get(opcode)
        if read is not None:
            try:
                records.append(read(ReadDataStream(io.BytesIO(content[pos + HEAD.size:end])),
                                    length))
            except Exception:  # struct, decoding: the content ends here for us
                break
        pos = end
    return records, pos


def restart_after(data: Buffer, start: int, known: list[int]) -> int | None:
    """The first offset at or after ``start`` where a record surely starts: a check record,
    a zstd chunk, or one of the ``known`` record offsets (:func:`summary_offsets`); None when
    there is none."""
    found = [offset for offset in known if offset >= start]
    for find in (_next_check, _next_chunk):
        at = find(data, start)
        if at is not None:
            found.append(at)
    return min(found) if found else None


def _next_check(data: Buffer, start: int) -> int | None:
    at = data.find(CHECK_TAG, start + HEAD.size)
    while at >= 0:
        pos = at - HEAD.size
        opcode, length = HEAD.unpack_from(data, pos)
        if opcode == CHECK_OPCODE and at + length <= len(data) and \
                ChunkCheck.parse(bytes(data[at:at + length])) is not None:
            return pos
        at = data.find(CHECK_TAG, at + 1)
    return None


def _next_chunk(data: Buffer, start: int) -> int | None:
    at = data.find(_ZSTD_CHUNK, start + _CHUNK_FIELDS.size)
    while at >= 0:
        pos = at - _CHUNK_FIELDS.size
        opcode, length = HEAD.unpack_from(data, pos)
        data_at = at + len(_ZSTD_CHUNK)
        if opcode == CHUNK_OPCODE and data_at + 8 <= len(data):
            (data_length,) = struct.unpack_from("<Q", data, data_at)
            if length == data_at + 8 + data_length - pos - HEAD.size:
                return pos
        at = data.find(_ZSTD_CHUNK, at + 1)
    return None


def summary_offsets(data: Buffer) -> list[int]:
    """The offsets of the records the summary indexes (chunks, their message indexes,
    metadata, attachments, the data end), when the file ends in an intact footer and summary;
    else none."""
    size = len(data)
    footer_at = size - MAGIC_BYTES - _FOOTER.size
    if footer_at < MAGIC_BYTES:
        return []
    opcode, _, summary_start, _, crc = _FOOTER.unpack_from(data, footer_at)
    if opcode != 0x02 or not crc or not MAGIC_BYTES <= summary_start <= footer_at or \
            zlib.crc32(data[summary_start:footer_at + _FOOTER.size - 4]) != crc:
        return []
    offsets: list[int] = []
    pos = summary_start
    try:
        while pos + HEAD.size <= footer_at:
            opcode, length = HEAD.unpack_from(data, pos)
            body = pos + HEAD.size
            if opcode == 0x08:  # chunk index: start, end, chunk offset, length, index offsets
                offsets.append(struct.unpack_from("<Q", data, body + 16)[0])
                (map_bytes,) = struct.unpack_from("<I", data, body + 32)
                offsets.extend(_index_offsets(data, body + 36, map_bytes))
            elif opcode in (0x0A, 0x0D):  # attachment, metadata index: the offset first
                offsets.append(struct.unpack_from("<Q", data, body)[0])
            pos = body + length
    except struct.error:  # a summary its CRC vouches for, yet not as the writer lays one out
        return []
    data_end = summary_start - HEAD.size - 4
    if data_end >= MAGIC_BYTES and data[data_end] == 0x0F:
        offsets.append(data_end)
    return sorted(offsets)


def _index_offsets(data: Buffer, at: int, map_bytes: int) -> list[int]:
    """The message index offsets of a chunk index's map (channel id u16 -> offset u64)."""
    return [struct.unpack_from("<Q", data, at + k + 2)[0] for k in range(0, map_bytes, 10)]
