"""A chunk's messages as arrays: one pass over its record heads, no object per message.

mcap's ``breakup_chunk`` reads a chunk's records through a stream, a :class:`Message` each:
several us per message, most of a 60 s servo session's read. :func:`chunk_records` opens the
chunk as it does (decompression, the CRC of the content) and then only steps from record head
to record head: schemas and channels are parsed, and the messages are kept as one
:class:`ChunkMessages` (each one's channel, log time, and where its data lies in the content),
read with numpy once the heads are known. A content not laid out as records end to end (a
length past its end, a message too short for its fields) is handed to ``breakup_chunk``
whole, so it reads as it always did.
"""

from __future__ import annotations

import io
import struct
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import UnsupportedCompressionError
from mcap.records import Channel, Chunk, Schema
from mcap.stream_reader import CRCValidationError, breakup_chunk

HEAD = struct.Struct("<BQ")
_LENGTH = struct.Struct("<xQ")  # a record head's length
MESSAGE_OPCODE = 0x05
_MESSAGE_FIELDS = 22  # channel id u16, sequence u32, log time u64, publish time u64
_PARSED = {0x03: Schema.read, 0x04: Channel.read}


@dataclass(frozen=True)
class ChunkMessages:
    """The messages of one chunk, in their order there: message ``k`` is on channel
    ``channel_ids[k]``, logged at ``log_times[k]``, its data ``content[starts[k]:starts[k] +
    sizes[k]]``."""

    content: bytes
    channel_ids: np.ndarray  # uint16
    log_times: np.ndarray    # uint64
    starts: np.ndarray       # int64
    sizes: np.ndarray        # int64

    def __len__(self) -> int:
        return int(self.starts.size)


def chunk_records(chunk_body: bytes) -> list[Any]:
    """The records of a chunk record's body: its schemas and channels, then its messages as
    one :class:`ChunkMessages`. Raises as ``breakup_chunk`` does for a chunk that cannot be
    opened (compression, CRC, records)."""
    chunk = Chunk.read(ReadDataStream(io.BytesIO(chunk_body)))
    if chunk.compression not in ("", "zstd", "lz4"):
        raise ValueError(f"unknown chunk compression {chunk.compression!r}")
    content = _content(chunk)
    split = _split(content)
    if split is None:  # not records end to end: mcap's own reading, errors and all
        return breakup_chunk(Chunk(compression="", data=content, message_start_time=0,
                                   message_end_time=0, uncompressed_crc=0,
                                   uncompressed_size=len(content)))
    return split


def _content(chunk: Chunk) -> bytes:
    """The chunk's records, decompressed and checked against its CRC (as ``breakup_chunk``)."""
    if chunk.compression == "zstd":
        content: bytes = zstandard.decompress(chunk.data, chunk.uncompressed_size)
    elif chunk.compression == "lz4":
        try:
            import lz4.frame
        except ImportError:
            raise UnsupportedCompressionError("lz4") from None
        content = lz4.frame.decompress(chunk.data)
    else:
        content = chunk.data
    if chunk.uncompressed_crc != 0:
        crc = zlib.crc32(content)
        if crc != chunk.uncompressed_crc:
            raise CRCValidationError(expected=chunk.uncompressed_crc, actual=crc, record=chunk)
    return content


def _split(content: bytes) -> list[Any] | None:
    """Schemas and channels parsed, messages found by their heads; None when the content is
    not whole records end to end, or a schema or channel does not fill its record."""
    heads: list[int] = []
    keep = heads.append
    length_at = _LENGTH.unpack_from
    pos, end, head = 0, len(content), HEAD.size
    try:
        while pos < end:  # the one loop per record: some 0.15 us each
            keep(pos)
            (length,) = length_at(content, pos)
            pos += head + length
    except struct.error:  # a record head cut by the end
        return None
    if pos != end:  # the last record runs past the end
        return None
    data = np.frombuffer(content, dtype=np.uint8)
    at = np.asarray(heads, dtype=np.int64)
    opcodes = data[at] if at.size else np.empty(0, dtype=np.uint8)
    records: list[Any] = []
    for head in at[(opcodes == 0x03) | (opcodes == 0x04)].tolist():
        record = _parsed(content, head)
        if record is None:
            return None
        records.append(record)
    messages = _messages(content, at[opcodes == MESSAGE_OPCODE])
    if (messages.sizes < 0).any():  # too short for a message's fields
        return None
    records.append(messages)
    return records


def _parsed(content: bytes, head: int) -> Any:
    """The schema or channel record at ``head``; None when it does not read as one filling
    its record exactly (mcap's reading would then go on where its fields end, not where the
    record does)."""
    opcode, length = HEAD.unpack_from(content, head)
    data = io.BytesIO(content)
    data.seek(head + HEAD.size)
    stream = ReadDataStream(data)
    try:
        record = _PARSED[opcode](stream)
    except Exception:  # struct, utf-8, end of data: mcap's reading says what
        return None
    return record if stream.count == length else None


def _messages(content: bytes, heads: np.ndarray) -> ChunkMessages:
    """The messages whose records start at ``heads``, their fields read with numpy."""
    data = np.frombuffer(content, dtype=np.uint8)
    lengths = read_at(data, heads + 1, np.dtype("<u8")).astype(np.int64)
    return ChunkMessages(content, read_at(data, heads + HEAD.size, np.dtype("<u2")),
                         read_at(data, heads + HEAD.size + 6, np.dtype("<u8")),
                         heads + HEAD.size + _MESSAGE_FIELDS, lengths - _MESSAGE_FIELDS)


def read_at(data: np.ndarray, offsets: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """The value of ``dtype`` at each of ``offsets`` in the bytes ``data`` (uint8)."""
    if offsets.size == 0:
        return np.empty(0, dtype=dtype.newbyteorder("="))
    windows = np.lib.stride_tricks.sliding_window_view(data, dtype.itemsize)
    return windows[offsets].view(dtype)[:, 0].astype(dtype.newbyteorder("="), copy=False)

