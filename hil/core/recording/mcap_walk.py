"""Walk an MCAP file record by record, checking CRCs, and account for what cannot be read.

The stock readers stop at the first bad byte. A session file may be truncated (SIGKILL, power
cut), carry a damaged chunk in the middle (a bad sector, a bit flip) or a damaged summary.
:func:`walk` reads every top-level record on its own; a chunk whose data or CRC is bad is
skipped and counted (its message count comes from the message indexes that follow it), and
the walk goes on with the next record. What could not be read is returned as
:class:`Damage` entries, each with its byte offset and size.
"""

from __future__ import annotations

import io
import mmap
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from mcap.data_stream import ReadDataStream
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    DataEnd,
    Footer,
    Message,
    MessageIndex,
    Metadata,
    Schema,
    Statistics,
)
from mcap.stream_reader import breakup_chunk

Buffer = bytes | memoryview | mmap.mmap
MAGIC = b"\x89MCAP0\r\n"
_HEAD = struct.Struct("<BQ")
CHUNK_OPCODE = 0x06

_READERS: dict[int, Callable[[ReadDataStream, int], Any]] = {
    0x03: lambda s, n: Schema.read(s),
    0x04: lambda s, n: Channel.read(s),
    0x05: lambda s, n: Message.read(s, n),
    0x07: lambda s, n: MessageIndex.read(s),
    0x09: lambda s, n: Attachment.read(s),
    0x0B: lambda s, n: Statistics.read(s),
    0x0C: lambda s, n: Metadata.read(s),
    0x0F: lambda s, n: DataEnd.read(s),
    0x02: lambda s, n: Footer.read(s),
}


@dataclass
class Damage:
    """A part of the file that could not be read."""

    kind: str                 # "truncated", "chunk", "record", "summary" or "trailing"
    offset: int               # byte offset in the file where it starts
    bytes: int                # bytes that could not be read
    messages: int | None = None  # messages lost, when the file says how many
    start_ns: int | None = None  # log-time range of the lost messages, when known
    end_ns: int | None = None
    reason: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if v is not None and v != ""}


@dataclass
class Walk:
    """What :func:`walk` found besides the records it yielded."""

    finished: bool = False          # a footer was read
    damage: list[Damage] = field(default_factory=list)
    statistics: Statistics | None = None
    in_summary: bool = False


def _parse(opcode: int, content: bytes) -> Any:
    reader = _READERS.get(opcode)
    if reader is None:
        return None
    return reader(ReadDataStream(io.BytesIO(content)), len(content))


def _chunk_records(content: bytes) -> list[Any]:
    chunk = Chunk.read(ReadDataStream(io.BytesIO(content)))
    if chunk.compression not in ("", "zstd", "lz4"):
        raise ValueError(f"unknown chunk compression {chunk.compression!r}")
    records = breakup_chunk(chunk, validate_crc=True)
    return records


def _chunk_times(content: bytes) -> tuple[int, int] | None:
    if len(content) < 16:
        return None
    start, end = struct.unpack_from("<QQ", content, 0)
    return (start, end) if start <= end else None


def walk(data: Buffer, state: Walk) -> Iterator[Any]:
    """Yield every readable record of an MCAP file's bytes (chunks opened), in file order."""
    if bytes(data[:len(MAGIC)]) != MAGIC:
        raise ValueError("not an MCAP session file (bad magic)")
    pos, size = len(MAGIC), len(data)
    broken_chunk: Damage | None = None  # its messages are counted from the indexes after it
    while pos < size:
        if size - pos < _HEAD.size:
            state.damage.append(Damage("truncated", pos, size - pos, reason="record header cut"))
            return
        opcode, length = _HEAD.unpack_from(data, pos)
        body = pos + _HEAD.size
        end = body + length
        if end > size or length > size:
            if opcode == 0 or opcode > 0x10:  # garbage where a record should start
                state.damage.append(Damage("summary" if state.in_summary else "record", pos,
                                           size - pos, reason=f"bad record header at {pos}"))
            else:
                damage = Damage("truncated", pos, size - pos, reason="file ends inside a record")
                if opcode == CHUNK_OPCODE:
                    times = _chunk_times(bytes(data[body:min(size, body + 16)]))
                    if times:
                        damage.start_ns, damage.end_ns = times
                state.damage.append(damage)
            return
        content = bytes(data[body:end])
        if opcode == CHUNK_OPCODE:
            broken_chunk = None
            try:
                records = _chunk_records(content)
            except Exception as exc:  # zstd, CRC, struct: any of them means the chunk is lost
                broken_chunk = Damage("chunk", pos, end - pos, messages=0,
                                      reason=f"{type(exc).__name__}: {exc}".strip(": "))
                times = _chunk_times(content)
                if times:
                    broken_chunk.start_ns, broken_chunk.end_ns = times
                state.damage.append(broken_chunk)
            else:
                yield from records
        else:
            try:
                record = _parse(opcode, content)
            except Exception as exc:
                state.damage.append(Damage("summary" if state.in_summary else "record", pos,
                                           end - pos, reason=f"{type(exc).__name__}: {exc}"))
                record = None
            if isinstance(record, MessageIndex):
                if broken_chunk is not None and broken_chunk.messages is not None:
                    broken_chunk.messages += len(record.records)
            elif isinstance(record, DataEnd):
                state.in_summary = True
                crc = record.data_section_crc
                if crc and zlib.crc32(bytes(data[:pos])) != crc and not any(
                        d.kind == "chunk" for d in state.damage):
                    state.damage.append(Damage("record", 0, 0, reason="data section CRC "
                                               "mismatch"))
            elif isinstance(record, Statistics):
                state.statistics = record
            elif isinstance(record, Footer):
                _check_summary(data, pos, record, state)
                _check_end(data, end, state)
                state.finished = True
                yield record
                return
            elif record is not None:
                yield record
        pos = end


def _check_end(data: Buffer, footer_end: int, state: Walk) -> None:
    """After the footer comes the closing magic and nothing else: bytes beyond it are another
    write mixed into the file (two runs on one file), never part of this session."""
    size = len(data)
    if bytes(data[footer_end:footer_end + len(MAGIC)]) != MAGIC or \
            size != footer_end + len(MAGIC):
        extra = size - footer_end - len(MAGIC)
        state.damage.append(Damage(
            "trailing", footer_end, size - footer_end,
            reason=f"{extra} byte(s) after the end of the session" if extra > 0
            else "the closing magic after the footer is missing"))


def _check_summary(data: Buffer, footer_pos: int, footer: Footer, state: Walk) -> None:
    """The footer's CRC covers the summary section and its own first two fields."""
    start = footer.summary_start
    if not footer.summary_crc or not start or start > footer_pos:
        return
    covered_end = footer_pos + _HEAD.size + 16
    if zlib.crc32(bytes(data[start:covered_end])) != footer.summary_crc:
        state.damage.append(Damage("summary", start, footer_pos - start,
                                   reason="summary CRC mismatch"))
