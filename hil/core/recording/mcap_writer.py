"""An indexed, chunked MCAP writer whose zstd level is an option.

mcap's own ``Writer`` compresses chunks at zstandard's default level and offers no option for
another. This writer builds the same file from the mcap package's public record classes
(``mcap.records``, ``mcap.data_stream.RecordBuilder``): a header; messages in zstd chunks,
each followed by its message indexes; schemas, channels, metadata and attachments between
chunks; then the summary (schemas, channels, statistics, chunk, attachment and metadata
indexes, summary offsets), the footer with the summary CRC, and the magic. Readers that need
the indexes (Foxglove's) read it as they read mcap's own files.

Where it differs from mcap's ``Writer``, for a damaged file's sake: schemas and channels are
records of their own between chunks (a lost chunk takes no topic with it); a chunk closes once
it spans ``chunk_span_ns`` of log time as well as at ``chunk_size`` bytes (a lockstep session,
many times faster than real time, would otherwise be one chunk); each chunk is preceded by
hil's check record (:mod:`hil.core.recording.chunk_check`: the piece CRCs a reader salvages a
damaged chunk by) and its zstd stream is cut into small blocks; the data end record carries
the data section's CRC.

The methods are those of ``mcap.writer.Writer`` that a session uses: ``start``,
``register_schema``, ``register_channel``, ``add_message``, ``add_metadata``,
``add_attachment``, ``flush`` (close the chunk in progress) and ``finish``.
"""

from __future__ import annotations

import struct
import zlib
from collections import defaultdict
from collections.abc import Iterable
from typing import IO

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from hil.core.recording.chunk_check import ChunkCheck, compress_in_blocks

MAGIC = b"\x89MCAP0\r\n"  # MCAP specification, "Magic"
# a Message record up to its data: opcode, record length, channel id, sequence, log time,
# publish time (mcap's Message.write, in one call: the writer's busiest record)
MESSAGE_HEAD = struct.Struct("<BQHIQQ")
MESSAGE_FIELDS_BYTES = MESSAGE_HEAD.size - 9
RECORD_HEAD = struct.Struct("<BQ")  # opcode, record length
DEFAULT_CHUNK_BYTES = 1 << 20


class McapWriter:
    """Writes one MCAP file to ``stream``; chunks are zstd-compressed at ``zstd_level``."""

    def __init__(self, stream: IO[bytes], *, chunk_size: int = DEFAULT_CHUNK_BYTES,
                 chunk_span_ns: int | None = None, zstd_level: int = 3) -> None:
        self._stream = stream
        self._data_crc = 0  # of every byte written before the data end record
        self._chunk_size = chunk_size
        self._chunk_span_ns = chunk_span_ns
        self._compressor = zstandard.ZstdCompressor(level=zstd_level)
        self._out = RecordBuilder()    # records outside chunks, written out at once
        self._chunk = bytearray()  # the records of the chunk in progress
        # per channel, each message's log time and offset in the chunk, one after the other
        self._chunk_indexes: dict[int, list[int]] = {}
        self._chunk_messages = 0
        self._chunk_start_ns = self._chunk_end_ns = 0
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._chunk_index_records: list[ChunkIndex] = []
        self._attachment_indexes: list[AttachmentIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._statistics = Statistics(
            message_count=0, schema_count=0, channel_count=0, attachment_count=0,
            metadata_count=0, chunk_count=0, message_start_time=0, message_end_time=0,
            channel_message_counts=defaultdict(int))

    # -- the file -----------------------------------------------------------------------
    def start(self, profile: str = "", library: str = "hil") -> None:
        self._write(MAGIC)
        Header(profile=profile, library=library).write(self._out)
        self._write_out()

    def finish(self) -> None:
        """The last chunk, the data end, the summary, the footer and the magic."""
        self._finish_chunk()
        DataEnd(data_section_crc=self._data_crc).write(self._out)
        self._write_out()
        summary_start = self._stream.tell()
        summary = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: Opcode, records: list) -> None:  # type: ignore[type-arg]
            start = summary.count
            for record in records:
                record.write(summary)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                         group_length=summary.count - start))

        group(Opcode.SCHEMA, list(self._schemas.values()))
        group(Opcode.CHANNEL, list(self._channels.values()))
        group(Opcode.STATISTICS, [self._statistics])
        group(Opcode.CHUNK_INDEX, self._chunk_index_records)
        group(Opcode.ATTACHMENT_INDEX, self._attachment_indexes)
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        offsets_start = summary_start + summary.count
        for offset in offsets:
            offset.write(summary)
        data = summary.end()
        self._stream.write(data)
        footer = RecordBuilder()
        Footer(summary_start=summary_start, summary_offset_start=offsets_start,
               summary_crc=0).write(footer)
        head = footer.end()[:-4]  # the footer up to its CRC: the CRC covers it too
        self._stream.write(head + zlib.crc32(head, zlib.crc32(data)).to_bytes(4, "little"))
        self._stream.write(MAGIC)

    # -- records ------------------------------------------------------------------------
    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas[schema.id] = schema
        self._statistics.schema_count += 1
        schema.write(self._out)
        self._write_out()
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        channel = Channel(id=len(self._channels) + 1, topic=topic,
                          message_encoding=message_encoding, schema_id=schema_id, metadata={})
        self._channels[channel.id] = channel
        self._statistics.channel_count += 1
        channel.write(self._out)
        self._write_out()
        return channel.id

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int,
                    sequence: int = 0) -> None:
        self.add_messages(((channel_id, log_time, publish_time, data),), sequence)

    def add_messages(self, messages: Iterable[tuple[int, int, int, bytes]],
                     sequence: int = 0) -> None:
        """``(channel_id, log_time, publish_time, data)`` each, numbered from ``sequence``:
        what :meth:`add_message` one by one writes, in one loop over local state (a
        session's writer adds its messages a flush's worth at a time). The statistics count
        each chunk's messages when it closes."""
        span, limit, pack = self._chunk_span_ns, self._chunk_size, MESSAGE_HEAD.pack
        chunk, indexes = self._chunk, self._chunk_indexes
        count, start, end = self._chunk_messages, self._chunk_start_ns, self._chunk_end_ns
        for channel_id, log_time, publish_time, data in messages:
            if count and span is not None and log_time - start >= span:
                self._chunk_messages, self._chunk_start_ns, self._chunk_end_ns = \
                    count, start, end
                self._finish_chunk()
                chunk, indexes, count = self._chunk, self._chunk_indexes, 0
            if count == 0:
                start = end = log_time
            elif log_time < start:
                start = log_time
            elif log_time > end:
                end = log_time
            count += 1
            index = indexes.get(channel_id)
            if index is None:
                index = indexes[channel_id] = []
            index += (log_time, len(chunk))
            chunk += pack(Opcode.MESSAGE, MESSAGE_FIELDS_BYTES + len(data), channel_id,
                          sequence, log_time, publish_time)
            chunk += data
            sequence += 1
            if len(chunk) > limit:
                self._chunk_messages, self._chunk_start_ns, self._chunk_end_ns = \
                    count, start, end
                self._finish_chunk()
                chunk, indexes, count = self._chunk, self._chunk_indexes, 0
        self._chunk_messages, self._chunk_start_ns, self._chunk_end_ns = count, start, end

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        offset = self._stream.tell() + self._out.count
        Metadata(name=name, metadata=data).write(self._out)
        self._metadata_indexes.append(MetadataIndex(offset=offset,
                                                    length=self._out.count, name=name))
        self._statistics.metadata_count += 1
        self._write_out()

    def add_attachment(self, create_time: int, log_time: int, name: str, media_type: str,
                       data: bytes) -> None:
        offset = self._stream.tell() + self._out.count
        Attachment(create_time=create_time, log_time=log_time, name=name,
                   media_type=media_type, data=data).write(self._out)
        self._attachment_indexes.append(AttachmentIndex(
            offset=offset, length=self._out.count, create_time=create_time, log_time=log_time,
            data_size=len(data), name=name, media_type=media_type))
        self._statistics.attachment_count += 1
        self._write_out()

    def flush(self) -> None:
        """Finish the chunk in progress (if it holds a message) and push it to the stream."""
        self._finish_chunk()
        self._stream.flush()

    # -- chunks -------------------------------------------------------------------------
    def _finish_chunk(self) -> None:
        if self._chunk_messages == 0:
            return
        self._count_chunk()
        records = bytes(self._chunk)
        compressed = compress_in_blocks(records, self._compressor)
        chunk = RecordBuilder()
        Chunk(message_start_time=self._chunk_start_ns, message_end_time=self._chunk_end_ns,
              uncompressed_size=len(records), uncompressed_crc=zlib.crc32(records),
              compression="zstd", data=compressed).write(chunk)
        chunk_record = chunk.end()
        self._out.write(ChunkCheck.of(chunk_record, self._chunk_messages, self._chunk_start_ns,
                                      self._chunk_end_ns).record())
        base = self._stream.tell()
        start = base + self._out.count
        self._out.write(chunk_record)
        index_start = base + self._out.count
        offsets = {}
        for channel_id, entries in self._chunk_indexes.items():
            offsets[channel_id] = base + self._out.count
            self._out.write(message_index_record(channel_id, entries))
        self._chunk_index_records.append(ChunkIndex(
            message_start_time=self._chunk_start_ns, message_end_time=self._chunk_end_ns,
            chunk_start_offset=start, chunk_length=len(chunk_record),
            message_index_offsets=offsets,
            message_index_length=base + self._out.count - index_start, compression="zstd",
            compressed_size=len(compressed), uncompressed_size=len(records)))
        self._statistics.chunk_count += 1
        self._write_out()
        self._chunk = bytearray()
        self._chunk_indexes = {}
        self._chunk_messages = 0
        self._chunk_start_ns = self._chunk_end_ns = 0

    def _count_chunk(self) -> None:
        """The chunk in progress into the statistics (its messages, their times, per channel)."""
        stats = self._statistics
        if stats.message_count == 0 or self._chunk_start_ns < stats.message_start_time:
            stats.message_start_time = self._chunk_start_ns
        stats.message_end_time = max(stats.message_end_time, self._chunk_end_ns)
        stats.message_count += self._chunk_messages
        for channel_id, entries in self._chunk_indexes.items():
            stats.channel_message_counts[channel_id] += len(entries) // 2

    def _write_out(self) -> None:
        self._write(self._out.end())

    def _write(self, data: bytes) -> None:
        self._stream.write(data)
        self._data_crc = zlib.crc32(data, self._data_crc)


def message_index_record(channel_id: int, entries: list[int]) -> bytes:
    """A channel's message index (each message's log time and offset, one after the other)
    as mcap's ``MessageIndex.write`` writes it, in one ``struct`` call rather than two calls
    a message (the records of a chunk's indexes are a writer's second busiest)."""
    body = struct.pack(f"<HI{len(entries)}Q", channel_id, 8 * len(entries), *entries)
    return RECORD_HEAD.pack(Opcode.MESSAGE_INDEX, len(body)) + body
