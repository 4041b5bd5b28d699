"""The reader opens a chunk by stepping from record head to record head
(:mod:`hil.core.recording.chunk_messages`) instead of mcap's ``breakup_chunk``: it must find the
same schemas, channels and messages, in the same order, on any chunk content; raise as
``breakup_chunk`` does where it raises; and read files that mcap's own writer wrote (schemas and
channels inside the chunks; zstd, lz4 or no compression; no chunks at all, the messages one by
one) as mcap's own reader does."""

from __future__ import annotations

import io
import json
import zlib
from collections.abc import Callable

import pytest
import zstandard
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer

from hil.core.recording.chunk_messages import ChunkMessages, chunk_records
from hil.core.recording.reader import read_session


@st.composite
def chunk_contents(draw: st.DrawFn) -> bytes:
    """Records end to end as a chunk holds them - messages, schemas, channels, a record of
    an opcode left to applications - sometimes with a cut or bytes that are no record."""
    builder = RecordBuilder()
    for _ in range(draw(st.integers(0, 12))):
        kind = draw(st.sampled_from(["message", "message", "message", "schema", "channel",
                                     "other"]))
        if kind == "message":
            Message(channel_id=draw(st.integers(0, 3)), sequence=draw(st.integers(0, 9)),
                    log_time=draw(st.integers(0, (1 << 64) - 1)), publish_time=0,
                    data=draw(st.binary(max_size=24))).write(builder)
        elif kind == "schema":
            Schema(id=draw(st.integers(1, 3)), name="s", encoding="ros2msg",
                   data=draw(st.binary(max_size=8))).write(builder)
        elif kind == "channel":
            Channel(id=draw(st.integers(0, 3)), schema_id=1, topic=draw(st.text(max_size=6)),
                    message_encoding="cdr", metadata={}).write(builder)
        else:
            body = draw(st.binary(max_size=12))
            builder.write(bytes([0x81]) + len(body).to_bytes(8, "little") + body)
    content = builder.end()
    damage = draw(st.sampled_from(["none", "none", "cut", "junk", "flip"]))
    if damage == "cut":
        content = content[:draw(st.integers(0, len(content)))]
    elif damage == "junk":
        content += draw(st.binary(min_size=1, max_size=12))
    elif damage == "flip" and content:
        at = draw(st.integers(0, len(content) - 1))
        content = content[:at] + bytes([content[at] ^ draw(st.integers(1, 255))]) + \
            content[at + 1:]
    return content


def chunk_body(content: bytes, compression: str = "") -> bytes:
    """A chunk record's body holding ``content`` (its CRC: 0, none, as a writer may leave)."""
    data = zstandard.compress(content) if compression == "zstd" else content
    builder = RecordBuilder()
    Chunk(compression=compression, data=data, message_start_time=0, message_end_time=0,
          uncompressed_crc=0, uncompressed_size=len(content)).write(builder)
    return builder.end()[9:]


def flat(records: list) -> list:
    """Records with a block of messages as the messages one by one."""
    out = []
    for record in records:
        if isinstance(record, ChunkMessages):
            for k in range(len(record)):
                start, size = int(record.starts[k]), int(record.sizes[k])
                out.append(("message", int(record.channel_ids[k]), int(record.log_times[k]),
                            record.content[start:start + size]))
        elif isinstance(record, Message):
            out.append(("message", record.channel_id, record.log_time, record.data))
        else:
            out.append(record)
    return out


def outcome(read: Callable[[bytes], list], body: bytes) -> tuple[str, object]:
    """What reading ``body`` gives: its records, or the type of what it raised."""
    try:
        return "read", flat(read(body))
    except Exception as exc:
        return "raised", type(exc)


def mcap_reads(body: bytes) -> list:
    """The chunk as mcap's stream reader opens it."""
    return breakup_chunk(Chunk.read(ReadDataStream(io.BytesIO(body))), validate_crc=True)


@pytest.mark.slow
@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(content=chunk_contents(), compression=st.sampled_from(["", "zstd"]))
def test_any_chunk_reads_as_mcaps_breakup_chunk_reads_it(content, compression):
    body = chunk_body(content, compression)
    hil, mcap = outcome(chunk_records, body), outcome(mcap_reads, body)
    assert hil[0] == mcap[0]
    if hil[0] == "read":
        schemas_and_channels = [r for r in hil[1] if not isinstance(r, tuple)]
        messages = [r for r in hil[1] if isinstance(r, tuple)]
        # the same records; schemas and channels listed before the chunk's messages
        assert schemas_and_channels == [r for r in mcap[1] if not isinstance(r, tuple)]
        assert messages == [r for r in mcap[1] if isinstance(r, tuple)]


def test_a_chunk_whose_crc_does_not_match_raises_as_mcap_says():
    content = RecordBuilder()
    Message(channel_id=1, sequence=0, log_time=5, publish_time=5, data=b"x").write(content)
    records = content.end()
    builder = RecordBuilder()
    Chunk(compression="", data=records, message_start_time=5, message_end_time=5,
          uncompressed_crc=zlib.crc32(records) ^ 1, uncompressed_size=len(records)).write(builder)
    with pytest.raises(ValueError, match="crc validation failed"):
        chunk_records(builder.end()[9:])


@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.LZ4,
                                         CompressionType.NONE, "no chunks"])
def test_a_file_of_mcaps_own_writer_reads_as_mcaps_reader_reads_it(tmp_path, compression):
    path = tmp_path / "theirs.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream, chunk_size=2048, use_chunking=compression != "no chunks",
                        compression=CompressionType.NONE if compression == "no chunks" else
                        compression)
        writer.start()
        schema = writer.register_schema("n", "jsonschema", b'{"type": "object"}')
        channels = [writer.register_channel(f"/t{k}", "json", schema) for k in range(3)]
        for k in range(600):  # log times not in order within a topic: read back in order
            t = (k * 7919) % 1000
            writer.add_message(channels[k % 3], t, json.dumps({"k": k}).encode(), t, k)
        writer.finish()
    with open(path, "rb") as stream:
        theirs = sorted(((c.topic, m.log_time, json.loads(m.data)["k"]) for _, c, m in
                         make_reader(stream).iter_messages(log_time_order=False)),
                        key=lambda item: (item[0], item[1]))  # stable: file order kept
    data = read_session(path)
    assert not data.recovered and not data.damage
    ours = [(topic, t, m["k"]) for topic in sorted(data.messages) for t, m in data.topic(topic)]
    assert ours == theirs and len(ours) == 600


def test_a_chunk_of_whole_records_gives_its_messages_as_one_block():
    builder = RecordBuilder()
    Schema(id=1, name="s", encoding="ros2msg", data=b"float64 x\n").write(builder)
    Channel(id=2, schema_id=1, topic="/x", message_encoding="cdr", metadata={}).write(builder)
    for k in range(5):
        Message(channel_id=2, sequence=k, log_time=10 * k, publish_time=0,
                data=bytes(k)).write(builder)
    records = chunk_records(chunk_body(builder.end(), "zstd"))
    assert [type(r) for r in records] == [Schema, Channel, ChunkMessages]
    block = records[-1]
    assert block.log_times.tolist() == [0, 10, 20, 30, 40]
    assert block.sizes.tolist() == [0, 1, 2, 3, 4] and set(block.channel_ids.tolist()) == {2}


def test_a_schema_whose_fields_run_past_its_record_reads_as_mcap_reads_it():
    """mcap reads a chunk's records as one stream: a schema whose data length says more than
    its record holds takes the next record's first bytes as its data, and reading goes on
    from there. hil's reading finds the same (found by the property test above)."""
    builder = RecordBuilder()
    Schema(id=1, name="s", encoding="ros2msg", data=b"\x00").write(builder)
    Message(channel_id=1, sequence=0, log_time=1, publish_time=1, data=b"").write(builder)
    content = bytearray(builder.end())
    content[9 + 2 + 5 + 11:9 + 2 + 5 + 11 + 4] = (3).to_bytes(4, "little")  # data: 3 bytes
    body = chunk_body(bytes(content))
    assert outcome(chunk_records, body) == outcome(mcap_reads, body)
    assert outcome(mcap_reads, body)[1][0].data == b"\x00\x05\x16"
