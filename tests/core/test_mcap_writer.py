"""hil's MCAP writer (zstd level as an option) writes what mcap's own writer writes, as mcap's
readers read it (records, indexes, statistics, CRCs: the data section's too), though its
layout differs for a damaged file's sake (schemas and channels between chunks, hil's check
record before each chunk, small zstd blocks); and it compresses every chunk at the level it
is given."""

import io
import json

import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.reader import make_reader
from mcap.records import Chunk, MessageIndex
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from hil.core.recording.chunk_check import compress_in_blocks
from hil.core.recording.mcap_writer import McapWriter, message_index_record
from hil.core.recording.reader import read_session


def write_session(writer):
    """The same records into any writer with mcap's Writer methods: two topics, metadata and
    an attachment in the middle, a flush (a chunk closed early), more messages."""
    writer.start(profile="", library="hil test")
    writer.add_metadata("session", {"kind": "test"})
    schema = writer.register_schema(name="T", encoding="jsonschema", data=b'{"type":"object"}')
    a = writer.register_channel(topic="/a", message_encoding="json", schema_id=schema)
    b = writer.register_channel(topic="/b", message_encoding="json", schema_id=schema)
    for k in range(3000):
        payload = json.dumps({"k": k, "v": [k * 0.5] * (k % 7)}).encode()
        writer.add_message(channel_id=a if k % 3 else b, log_time=1000 * k, data=payload,
                           publish_time=1000 * k, sequence=k)
        if k == 1200:
            writer.flush()
            writer.add_attachment(create_time=5, log_time=6, name="config.toml",
                                  media_type="application/toml", data=b"[x]\ny = 1\n")
            writer.add_metadata("mid", {"k": str(k)})
    writer.finish()


def ours(level, chunk_size=64 * 1024):
    stream = io.BytesIO()
    write_session(McapWriter(stream, chunk_size=chunk_size, zstd_level=level))
    return stream.getvalue()


def chunks(data):
    return [r for r in StreamReader(io.BytesIO(data), emit_chunks=True).records
            if isinstance(r, Chunk)]


def read_back(data):
    """Every record mcap's stream reader gives (CRCs checked, chunks opened) but those that
    hold offsets or counts of the layout; and what its indexed reader gives."""
    records = [r for r in StreamReader(io.BytesIO(data), validate_crcs=True).records
               if not type(r).__name__.endswith("Index") and type(r).__name__ not in (
                   "Statistics", "SummaryOffset", "DataEnd", "Footer")]
    reader = make_reader(io.BytesIO(data))
    summary = reader.get_summary()
    indexed = [(c.topic, m.log_time, m.data) for _, c, m in reader.iter_messages()]
    stats = summary.statistics
    return (sorted(map(repr, records)), indexed, stats.message_count,
            dict(stats.channel_message_counts), sorted(summary.channels),
            [m.name for m in reader.iter_metadata()])


def test_mcaps_readers_read_the_same_session_in_mcaps_own_file_and_in_hils():
    theirs = io.BytesIO()
    write_session(Writer(theirs, chunk_size=64 * 1024, compression=CompressionType.ZSTD))
    assert read_back(ours(3)) == read_back(theirs.getvalue())


@pytest.mark.parametrize("level", [1, 9, 19])
def test_every_chunk_is_compressed_at_the_level_given(level):
    found = chunks(ours(level))
    assert len(found) >= 3  # the flush closed one early
    compressor = zstandard.ZstdCompressor(level=level)
    for chunk in found:
        assert chunk.compression == "zstd"
        records = zstandard.ZstdDecompressor().decompress(
            chunk.data, max_output_size=chunk.uncompressed_size)
        assert compress_in_blocks(records, compressor) == chunk.data


def test_a_higher_level_gives_a_smaller_file_with_the_same_messages():
    fast, small = ours(1), ours(19)
    assert len(small) < len(fast)
    for data in (fast, small):
        reader = make_reader(io.BytesIO(data))
        summary = reader.get_summary()
        assert summary.statistics.message_count == 3000
        assert dict(summary.statistics.channel_message_counts) == {1: 2000, 2: 1000}
        assert len(summary.chunk_indexes) == summary.statistics.chunk_count
        messages = [(c.topic, m.log_time) for _, c, m in reader.iter_messages()]
        assert len(messages) == 3000 and messages[5] == ("/a", 5000)
        assert [a.name for a in reader.iter_attachments()] == ["config.toml"]
        assert [m.name for m in reader.iter_metadata()] == ["session", "mid"]


def test_hils_reader_finds_the_file_intact(tmp_path):
    path = tmp_path / "s.mcap"
    path.write_bytes(ours(9))
    data = read_session(str(path))
    assert not data.recovered
    assert data.topic_counts == {"/a": 2000, "/b": 1000}


@pytest.mark.parametrize("count", [0, 1, 3, 2000])
def test_a_chunks_message_index_is_the_record_mcap_writes(count):
    entries = [(1_700_000_000_000_000_000 + 500_000 * k, 31 * k) for k in range(count)]
    index = MessageIndex(channel_id=7, records=entries)
    builder = RecordBuilder()
    index.write(builder)
    assert message_index_record(7, [n for entry in entries for n in entry]) == builder.end()


def test_messages_added_a_batch_at_a_time_are_the_messages_mcaps_writer_adds_one_by_one():
    """``add_messages`` (a flush's worth at once, how a session's writer adds them) across
    chunks closed by size and by time span, with times out of order, against mcap's own
    writer given the same messages one by one: the same records, indexes and statistics."""
    messages = [(1 + k % 3 // 2, 1000 * k + 2000 - (1500 if k % 5 == 0 else 0), 1000 * k,
                 json.dumps({"k": k, "v": [k * 0.5] * (k % 7)}).encode()) for k in range(3000)]

    def write(writer, batch=0):
        writer.start(profile="", library="hil test")
        schema = writer.register_schema(name="T", encoding="jsonschema", data=b"{}")
        for topic in ("/a", "/b"):
            writer.register_channel(topic=topic, message_encoding="json", schema_id=schema)
        for at in range(0, len(messages), batch or len(messages)):
            if batch:
                writer.add_messages(messages[at:at + batch], sequence=at)
            else:
                for sequence, (channel, log_time, publish_time, data) in enumerate(messages):
                    writer.add_message(channel_id=channel, log_time=log_time, data=data,
                                       publish_time=publish_time, sequence=sequence)
        writer.finish()

    theirs = io.BytesIO()
    write(Writer(theirs, chunk_size=64 * 1024, compression=CompressionType.ZSTD))
    for span_ns in (None, 200_000):
        ours_ = io.BytesIO()
        write(McapWriter(ours_, chunk_size=16 * 1024, chunk_span_ns=span_ns), batch=37)
        assert len(chunks(ours_.getvalue())) > 10
        assert read_back(ours_.getvalue()) == read_back(theirs.getvalue())
        stats = [make_reader(io.BytesIO(data)).get_summary().statistics
                 for data in (ours_.getvalue(), theirs.getvalue())]
        assert stats[0].message_start_time == stats[1].message_start_time == 500
        assert stats[0].message_end_time == stats[1].message_end_time == 3_001_000
