"""Walk an MCAP file record by record, checking CRCs, and account for what cannot be read.

The stock readers stop at the first bad byte. A session file may be truncated (SIGKILL, power
cut), carry a damaged chunk in the middle (a bad sector, a bit flip) or a damaged summary.
:func:`walk` reads every top-level record on its own; an intact chunk gives its messages as
one :class:`~hil.core.recording.chunk_messages.ChunkMessages`. A chunk whose data or CRC is
bad gives what it holds before its damage, message by message
(:func:`hil.core.recording.mcap_salvage.salvage_chunk`, as far as hil's check record before
it vouches for its bytes, or up to where the file was cut) and its loss is counted (from the
message indexes that follow it, else from its check; those of intact chunks are only checked
to fit their record). Bytes that are no record are skipped up to the next record that surely
starts (:func:`~hil.core.recording.mcap_salvage.restart_after`), and the walk goes on. What
could not be read is returned as :class:`Damage` entries, each with its byte offset and size.
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
    DataEnd,
    Footer,
    Message,
    MessageIndex,
    Metadata,
    Schema,
    Statistics,
)

from hil.core.recording.chunk_check import OPCODE as CHECK_OPCODE
from hil.core.recording.chunk_check import ChunkCheck
from hil.core.recording.chunk_messages import chunk_records
from hil.core.recording.mcap_salvage import restart_after, salvage_chunk, summary_offsets

Buffer = bytes | mmap.mmap
MAGIC = b"\x89MCAP0\r\n"
_HEAD = struct.Struct("<BQ")
CHUNK_OPCODE = 0x06
INDEX_OPCODE = 0x07
_INDEX_HEAD = struct.Struct("<HI")  # a message index's channel id and entries' bytes

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
    salvaged: int | None = None  # messages read from a damaged chunk, before its damage
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


def _read(opcode: int, content: bytes, counting: bool) -> Any:
    """The record of ``opcode`` (None: one the walk skips). A message index is read only when
    its entries count a damaged chunk's loss (``counting``): reading them costs microseconds
    per message; else it is only checked to fit its record."""
    if opcode == INDEX_OPCODE and not counting and _index_fits(content):
        return None
    return _parse(opcode, content)


def _index_fits(content: bytes) -> bool:
    """Whether a message index's entries fit its record (``MessageIndex.read`` reads them)."""
    if len(content) < _INDEX_HEAD.size:
        return False
    _, length = _INDEX_HEAD.unpack_from(content)
    return _INDEX_HEAD.size + 16 * -(-length // 16) <= len(content)


def _chunk_times(content: bytes) -> tuple[int, int] | None:
    if len(content) < 16:
        return None
    start, end = struct.unpack_from("<QQ", content, 0)
    return (start, end) if start <= end else None


@dataclass
class _Broken:
    """A damaged chunk while the records after it are read: its message indexes say which of
    its messages were lost (those at or beyond ``kept`` bytes of its content)."""

    damage: Damage
    check: ChunkCheck | None
    kept: int                   # bytes of its content salvaged, whole records
    salvaged: int               # messages salvaged
    indexed: int = 0            # messages its indexes list
    lost_times: list[int] = field(default_factory=list)

    def count(self, index: MessageIndex) -> None:
        self.indexed += len(index.records)
        self.lost_times += [t for t, offset in index.records if offset >= self.kept]

    def settle(self) -> None:
        """The loss, from the indexes when they are whole (as many as the check says, or no
        check to say otherwise), else from the check."""
        damage, check = self.damage, self.check
        if self.indexed and (check is None or self.indexed == check.message_count):
            damage.messages = len(self.lost_times)
            if self.lost_times:
                damage.start_ns, damage.end_ns = min(self.lost_times), max(self.lost_times)
        elif check is not None:
            damage.messages = check.message_count - self.salvaged
        elif damage.kind == "chunk":
            damage.messages = None


def _damaged_chunk(record: bytes, check: ChunkCheck | None, damage: Damage,
                   intact: int) -> tuple[list[Any], _Broken]:
    """What can be read of a chunk record whose first ``intact`` bytes are the writer's."""
    records, kept = salvage_chunk(record[:intact])
    salvaged = sum(isinstance(r, Message) for r in records)
    times = _chunk_times(record[_HEAD.size:]) if intact >= _HEAD.size + 16 else None
    if check is not None:
        times = (check.start_ns, check.end_ns)
    if times:
        damage.start_ns, damage.end_ns = times
    if salvaged:
        damage.salvaged = salvaged
    broken = _Broken(damage, check, kept, salvaged)
    broken.settle()
    return records, broken


def walk(data: Buffer, state: Walk) -> Iterator[Any]:
    """Yield every readable record of an MCAP file's bytes (chunks opened, damaged ones as far
    as they go), in file order: an intact chunk's messages as one ``ChunkMessages``."""
    size = len(data)
    known = summary_offsets(data)
    pos = len(MAGIC)
    if bytes(data[:len(MAGIC)]) != MAGIC:
        restart = restart_after(data, 0, known)
        if restart is None:
            raise ValueError("not an MCAP session file (bad magic)")
        state.damage.append(Damage("record", 0, restart, reason="bad magic"))
        pos = restart
    check: ChunkCheck | None = None  # the check record just read: of the chunk that follows
    broken: _Broken | None = None    # the damaged chunk its message indexes may still count
    while pos < size:
        if size - pos < _HEAD.size:
            state.damage.append(Damage("truncated", pos, size - pos, reason="record header cut"))
            return
        opcode, length = _HEAD.unpack_from(data, pos)
        end = pos + _HEAD.size + length
        if check is not None and (opcode != CHUNK_OPCODE or end != pos + check.chunk_length):
            opcode, end = CHUNK_OPCODE, pos + check.chunk_length  # its head is damaged
        if broken is not None and opcode != INDEX_OPCODE:
            broken = None
        if end > size or not _known_opcode(opcode):
            restart = restart_after(data, pos + 1, known)
            if restart is None and end > size and _known_opcode(opcode):
                damage = Damage("truncated", pos, size - pos, reason="file ends inside a record")
                if opcode == CHUNK_OPCODE:
                    record = bytes(data[pos:size])
                    intact = check.intact_bytes(record) if check is not None else len(record)
                    records, broken = _damaged_chunk(record, check, damage, intact)
                    yield from records
                state.damage.append(damage)
                return
            _add_unreadable(state, pos, (restart or size) - pos, f"bad record header at {pos}")
            if restart is None:
                return
            pos, check = restart, None
            continue
        content = bytes(data[pos + _HEAD.size:end])
        if opcode == CHUNK_OPCODE:
            try:
                yield from chunk_records(content)
            except Exception as exc:  # zstd, CRC, struct: what is before the damage is kept
                damage = Damage("chunk", pos, end - pos,
                                reason=f"{type(exc).__name__}: {exc}".strip(": "))
                record = bytes(data[pos:end])
                records, broken = _damaged_chunk(
                    record, check, damage, check.intact_bytes(record) if check else 0)
                state.damage.append(damage)
                yield from records
            check = None
            pos = end
            continue
        check = None
        try:
            record = _read(opcode, content, counting=broken is not None)
        except Exception as exc:  # the record's length may be damaged too: not past a chunk
            restart = restart_after(data, pos + 1, known)
            end = min(end, restart) if restart is not None else end
            _add_unreadable(state, pos, end - pos, f"{type(exc).__name__}: {exc}", messages=0)
            pos = end
            continue
        if opcode == CHECK_OPCODE:
            check = ChunkCheck.parse(content)
            if check is None:
                state.damage.append(Damage("record", pos, end - pos, messages=0,
                                           reason="damaged chunk check"))
        elif isinstance(record, MessageIndex):
            if broken is not None:
                broken.count(record)
                broken.settle()
        elif isinstance(record, DataEnd):
            state.in_summary = True
            crc = record.data_section_crc
            if crc and _crc(data, pos) != crc and not state.damage:
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


def _crc(data: Buffer, end: int, step: int = 1 << 20) -> int:
    """The CRC-32 of ``data[:end]``, read a piece at a time (no copy of the whole)."""
    crc = 0
    for at in range(0, end, step):
        crc = zlib.crc32(data[at:min(end, at + step)], crc)
    return crc


def _add_unreadable(state: Walk, offset: int, size: int, reason: str,
                    messages: int | None = None) -> None:
    """Bytes that are no readable record: one damage with the unreadable bytes just before
    them, if there are any (damage found again where the walk restarted)."""
    kind = "summary" if state.in_summary else "record"
    last = state.damage[-1] if state.damage else None
    if last is not None and last.kind == kind and last.offset + last.bytes == offset:
        last.bytes += size
        last.messages = None if None in (last.messages, messages) else \
            (last.messages or 0) + (messages or 0)
        return
    state.damage.append(Damage(kind, offset, size, messages=messages, reason=reason))


def _known_opcode(opcode: int) -> bool:
    """An MCAP opcode (0x01-0x0F), hil's check record, or one left to applications."""
    return 0x01 <= opcode <= 0x0F or opcode >= 0x80


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
