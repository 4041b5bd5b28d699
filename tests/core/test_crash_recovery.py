"""Session files tell the truth: a SIGKILLed loop still leaves a finished file, and a file
that is truncated, or damaged in a chunk or in its summary, is never reported intact."""

import json
import os
import signal
import time

import pytest
from mcap.reader import make_reader

from hil.cli.main import main
from hil.core.recording.reader import read_session
from hil.core.recording.recorder import Recorder

pytestmark = [pytest.mark.slow]

RATE_HZ = 2000
SCHEMA = {"type": "object", "title": "Seq"}

CHILD = """
import time
from hil.core.recording.recorder import Recorder
rec = Recorder({path!r})
print("writer", rec.writer_pid, flush=True)
topic = rec.topic("/seq", {{"type": "object", "title": "Seq"}})
t0 = time.monotonic()
k = 0
while True:
    target = t0 + k / {rate}
    while time.monotonic() < target:
        time.sleep(0.0002)
    topic.log(int(target * 1e9), {{"k": k, "pad": "x" * 40}})
    rec.flush_if_due()  # what the loop does after every tick
    if k % 100 == 0:
        print(k, flush=True)
    k += 1
"""


def _wait_gone(pid: int, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.02)
    pytest.fail(f"writer process {pid} still running {timeout_s} s after the loop died")


def test_sigkill_of_the_loop_process_leaves_a_finished_indexed_file(tmp_path, run_python):
    path = tmp_path / "crash.mcap"
    child = run_python(CHILD.format(path=str(path), rate=RATE_HZ))
    try:
        first = child.stdout.readline().split()
        assert first[0] == "writer", child.stderr.read()
        writer_pid = int(first[1])
        last_reported = -1
        t_start = time.monotonic()
        while time.monotonic() - t_start < 2.5:
            line = child.stdout.readline()
            if not line:
                pytest.fail(f"child died early: {child.stderr.read()}")
            last_reported = int(line)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=10)
    assert last_reported > RATE_HZ  # it really recorded for a while
    _wait_gone(writer_pid)

    with open(path, "rb") as f:  # the stock indexed reader opens it: summary and index written
        reader = make_reader(f)
        indexed = sum(1 for _ in reader.iter_messages(topics=["/seq"]))
    data = read_session(path)
    assert not data.recovered and data.damage == []
    ks = [m["k"] for _, m in data.topic("/seq")]
    assert indexed == len(ks) and ks == list(range(len(ks)))  # a gap-free prefix
    assert "without closing" in data.metadata["recorder"]["ended"]
    # handed over every 5 ms; allow 50 ms for a loaded 2-core machine
    assert last_reported - len(ks) <= 0.05 * RATE_HZ, f"lost {last_reported - len(ks)}"


@pytest.fixture
def finished_file(tmp_path):
    """A finished session file of 20,000 messages in many small chunks, and their ks."""
    path = tmp_path / "whole.mcap"
    rec = Recorder(path, chunk_size=16 * 1024)
    topic = rec.topic("/seq", SCHEMA)
    for k in range(20_000):
        topic.log(k * 500_000, {"k": k, "pad": "x" * 40})
    rec.close()
    return path


def _chunk_offsets(path):
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    return sorted((c.chunk_start_offset, c.chunk_length, c.message_end_time)
                  for c in summary.chunk_indexes)


def test_truncated_file_keeps_every_complete_chunk(finished_file, tmp_path, capsys):
    blob = finished_file.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(blob[: len(blob) // 2])
    data = read_session(cut)
    assert data.recovered and data.lost_bytes > 0
    ks = [m["k"] for _, m in data.topic("/seq")]
    assert 0 < len(ks) < 20_000 and ks == list(range(len(ks)))
    assert [d.kind for d in data.damage] == ["truncated"]
    assert_lost_bytes_mark_the_readable_prefix(cut, data, tmp_path)

    assert main(["report", str(cut), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["recovered"] is True and summary["lost_bytes"] == data.lost_bytes
    assert summary["damage"][0]["kind"] == "truncated"
    assert summary["damage"][0]["offset"] == len(blob) // 2 - data.lost_bytes


def assert_lost_bytes_mark_the_readable_prefix(path, data, tmp_path):
    """Cut at ``size - lost_bytes`` the file reads the same with nothing lost; one byte
    shorter, the last record read is incomplete and is lost."""
    blob = path.read_bytes()
    readable = len(blob) - data.lost_bytes
    assert 0 < readable <= len(blob)
    prefix = tmp_path / "prefix.mcap"
    prefix.write_bytes(blob[:readable])
    again = read_session(prefix)
    assert again.lost_bytes == 0 and again.messages == data.messages
    shorter = tmp_path / "shorter.mcap"
    shorter.write_bytes(blob[:readable - 1])
    cut = read_session(shorter)
    assert cut.lost_bytes > 0
    assert sum(map(len, cut.messages.values())) <= sum(map(len, data.messages.values()))


def test_a_damaged_chunk_in_the_middle_is_counted_and_the_rest_read(finished_file, tmp_path,
                                                                    capsys):
    chunks = _chunk_offsets(finished_file)
    assert len(chunks) >= 5
    offset, length, _ = chunks[len(chunks) // 2]
    blob = bytearray(finished_file.read_bytes())
    for i in range(offset + length - 200, offset + length - 100):  # inside its zstd data
        blob[i] ^= 0xFF
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(blob))

    data = read_session(damaged)
    assert data.recovered
    [damage] = data.damage
    assert damage.kind == "chunk" and damage.offset == offset and damage.bytes == length
    ks = [m["k"] for _, m in data.topic("/seq")]
    missing = sorted(set(range(20_000)) - set(ks))
    assert len(missing) == damage.messages > 0  # exactly that chunk's messages, counted
    assert missing == list(range(missing[0], missing[-1] + 1))  # one contiguous hole
    assert damage.start_ns == missing[0] * 500_000 and damage.end_ns == missing[-1] * 500_000

    assert main(["report", str(damaged)]) == 0
    text = capsys.readouterr().out
    assert "DAMAGED" in text and f"{damage.messages} message(s)" in text


def test_a_damaged_summary_is_reported_though_no_message_is_lost(finished_file, tmp_path):
    blob = bytearray(finished_file.read_bytes())
    footer_len = 8 + 1 + 8 + 20  # magic, footer opcode, length, footer body
    blob[-footer_len - 40] ^= 0xFF  # inside the summary section, before the footer
    blob[-footer_len - 39] ^= 0xFF
    damaged = tmp_path / "summary.mcap"
    damaged.write_bytes(bytes(blob))
    data = read_session(damaged)
    ks = [m["k"] for _, m in data.topic("/seq")]
    assert ks == list(range(20_000))
    assert data.recovered and data.damage, "a damaged summary must not read as intact"


def test_a_chunk_whose_opcode_changed_is_damage_not_intact(finished_file, tmp_path):
    # found by the fuzz campaign (tests/fuzz): one bit of a chunk's opcode flipped (0x06 ->
    # 0x07, a message index) dropped its messages without a word, and the file read intact.
    # The chunk index still points at it, so its messages are salvaged; the damage is named.
    offset, _, _ = _chunk_offsets(finished_file)[1]
    blob = bytearray(finished_file.read_bytes())
    blob[offset] ^= 0x01
    damaged = tmp_path / "opcode.mcap"
    damaged.write_bytes(bytes(blob))
    data = read_session(damaged)
    ks = [m["k"] for _, m in data.topic("/seq")]
    assert ks == list(range(20_000))
    assert data.recovered and data.damage
    assert "CRC mismatch" in data.error
