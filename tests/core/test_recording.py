"""Compact (CDR) topics and split session files, written by the writer process and read back
by hil's reader, by mcap's stock indexed reader and by a third-party ROS 2 CDR decoder."""

import math
import os
import signal
import time

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from hil.core.recording.reader import read_session, session_files
from hil.core.recording.recorder import Recorder, RecordingOptions
from hil.errors import HilError

FLAT = {
    "type": "object",
    "title": "hil.Everything",
    "properties": {
        "t_s": {"type": "number"},
        "narrow": {"type": "number", "x-cdr": "float32"},
        "count": {"type": "integer"},
        "word": {"type": "integer", "x-cdr": "uint16"},
        "small": {"type": "integer", "x-cdr": "int8"},
        "ok": {"type": "boolean"},
        "path": {"type": "string"},
        "samples_mA": {"type": "array", "items": {"type": "number"}},
        "counts": {"type": "array", "items": {"type": "integer", "x-cdr": "int32"}},
    },
}
NESTED = {"type": "object", "title": "N", "properties": {"data": {"type": "object"}}}


def _message(k: int) -> dict:
    return {"t_s": k * 0.0005, "narrow": k / 3, "count": k * 1_000_003, "word": k % 65536,
            "small": (k % 200) - 100, "ok": k % 2 == 0, "path": "qp" * (k % 3),
            "samples_mA": [k * 0.1, -k * 0.2][: k % 3], "counts": list(range(k % 4))}


def test_cdr_round_trip_through_the_writer_process(tmp_path):
    path = tmp_path / "cdr.mcap"
    rec = Recorder(path, wait_when_full=True)
    topic = rec.topic("/flat", FLAT, encoding="cdr")
    sent = [_message(k) for k in range(3000)]
    for k, message in enumerate(sent):
        topic.log(k * 500_000, message)
    rec.close()

    data = read_session(path)
    assert data.encodings["/flat"] == "cdr" and "ros2msg" in data.schemas["/flat"]
    got = [m for _, m in data.topic("/flat")]
    assert len(got) == len(sent)
    for want, have in zip(sent, got, strict=True):
        assert set(have) == set(FLAT["properties"])
        assert have["narrow"] == pytest.approx(want["narrow"], rel=1e-7)  # float32
        assert {k: v for k, v in have.items() if k != "narrow"} == \
            {k: v for k, v in want.items() if k != "narrow"}

    # a third-party ROS 2 decoder reads the same values (field names lower-cased for ROS 2)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        decoded = [d for _, _, _, d in reader.iter_decoded_messages(topics=["/flat"])]
    assert len(decoded) == len(sent)
    for want, have in zip(got, decoded, strict=True):
        assert have.samples_ma == want["samples_mA"] and have.path == want["path"]
        assert have.word == want["word"] and have.small == want["small"]
        assert math.isclose(have.narrow, want["narrow"])


def _raw_messages(path, topic: str) -> list[tuple[int, bytes]]:
    with open(path, "rb") as f:
        return [(m.log_time, m.data) for _, _, m in make_reader(f).iter_messages(topics=[topic])]


@pytest.mark.parametrize("encoding", ["cdr", "json"])
def test_packed_rows_record_the_same_bytes_as_dicts(tmp_path, encoding):
    """A row (the schema's properties in order, None where a message leaves a field out) and
    the dict it stands for give the same message bytes, in CDR and in JSON."""
    names = list(FLAT["properties"])
    files = {}
    for form in ("dict", "row"):
        files[form] = tmp_path / f"{form}.mcap"
        with Recorder(files[form], wait_when_full=True) as rec:
            topic = rec.topic("/flat", FLAT, encoding=encoding)
            for k in range(500):
                message = _message(k)
                if k % 7 == 0:
                    del message["path"]  # left out: None in the row
                row = tuple(message.get(name) for name in names)
                topic.log(k * 500_000, message if form == "dict" else row)
    by_dict, by_row = _raw_messages(files["dict"], "/flat"), _raw_messages(files["row"], "/flat")
    assert len(by_dict) == 500 and by_dict == by_row


@pytest.mark.parametrize("in_process", [False, True])
def test_topics_logged_together_record_what_each_topic_logs_alone(tmp_path, in_process):
    """A group of topics (Recorder.rows: one hand-over a tick for every axis of a bus) gives,
    topic by topic, the bytes and times of each topic's own log, through the writer process
    and in process."""
    names = list(FLAT["properties"])
    options = RecordingOptions(in_process=in_process)
    files = {}
    for form in ("alone", "together"):
        files[form] = tmp_path / f"{form}.mcap"
        with Recorder(files[form], wait_when_full=True, options=options) as rec:
            a, b = rec.topic("/a", FLAT, encoding="cdr"), rec.topic("/b", FLAT, encoding="json")
            both = rec.rows((a, b))
            for k in range(700):
                row_a = tuple(_message(k).get(name) for name in names)
                row_b = tuple(_message(k + 1).get(name) for name in names)
                if form == "alone":
                    a.log(k * 500_000, row_a)
                    b.log(k * 500_000, row_b)
                else:
                    assert both.log(k * 500_000, (row_a, row_b))
    for topic in ("/a", "/b"):
        alone, together = _raw_messages(files["alone"], topic), \
            _raw_messages(files["together"], topic)
        assert len(alone) == 700 and together == alone


def test_topics_logged_together_count_their_drops_each(tmp_path):
    """Rows refused (the backlog full) are counted on every topic of the group, and the
    counts reach the file's /events as each topic's."""
    rec = Recorder(tmp_path / "d.mcap", batch_size=1, max_backlog_bytes=1)
    a, b = rec.topic("/a", NESTED), rec.topic("/b", NESTED)
    both = rec.rows((a, b))
    accepted = sum(both.log(k, ({"data": {"pad": "x" * 10_000}}, {"data": {"k": k}}))
                   for k in range(2000))
    stats = rec.close()
    assert 0 < a.dropped == b.dropped == 2000 - accepted
    assert stats.messages_dropped == {"/a": a.dropped, "/b": b.dropped}
    data = read_session(tmp_path / "d.mcap")
    assert len(data.topic("/a")) == len(data.topic("/b")) == accepted


COLUMNS = {"type": "object", "title": "C", "properties": {
    "window": {"type": "integer"}, "a": {"type": "array", "items": {"type": "number"}},
    "b": {"type": "array", "items": {"type": "number"}},
    "c": {"type": "array", "items": {"type": "number"}}}}


@pytest.mark.parametrize("in_process", [False, True])
def test_a_column_topic_records_the_rows_since_its_last_message_as_its_columns(
        tmp_path, in_process):
    """Rows handed over one at a time are the columns of the next message, in the writer
    process and in process; a message with no rows has empty columns; a field given is
    kept as given."""
    path = tmp_path / "c.mcap"
    with Recorder(path, wait_when_full=True,
                  options=RecordingOptions(in_process=in_process)) as rec:
        columns = rec.columns(rec.topic("/c", COLUMNS, encoding="json"))
        for window, rows in enumerate((3, 0, 2)):
            for k in range(rows):
                columns.add((window + k / 10, -k))
            assert columns.log(window, {"window": window, "c": [7.5]}, ("a", "b"))
    recorded = [m for _, m in read_session(path).topic("/c")]
    assert recorded == [
        {"window": 0, "a": [0.0, 0.1, 0.2], "b": [0, -1, -2], "c": [7.5]},
        {"window": 1, "a": [], "b": [], "c": [7.5]},
        {"window": 2, "a": [2.0, 2.1], "b": [0, -1], "c": [7.5]}]


def test_a_column_message_with_a_refused_row_is_dropped_whole_and_counted(tmp_path):
    """A row refused (the writer process stopped, the pipe and the backlog full) drops its
    whole message, counted once: the rows of the message after it are its own only."""
    rec = Recorder(tmp_path / "d.mcap", batch_size=1, max_backlog_bytes=1)
    columns = rec.columns(rec.topic("/c", COLUMNS, encoding="json"))
    pad = rec.topic("/pad", NESTED)
    rec.wait_ready()

    def window(number: int, rows: int) -> bool:
        for k in range(rows):
            columns.add((number, k))
        return columns.log(number, {"window": number}, ("a", "b"))

    assert window(0, 4)
    os.kill(rec.writer_pid, signal.SIGSTOP)
    try:
        while pad.log(0, {"data": {"pad": "x" * 100_000}}):  # until the pipe is full
            pass
        columns.add((1, 0))  # refused
    finally:
        os.kill(rec.writer_pid, signal.SIGCONT)
    while not pad.log(1, {"data": {}}):  # the backlog handed over
        time.sleep(0.01)
        rec.flush()
    assert not window(1, 2)  # two rows more, taken: the message is dropped all the same
    assert window(2, 3)
    stats = rec.close()
    recorded = [m for _, m in read_session(tmp_path / "d.mcap").topic("/c")]
    assert recorded == [{"window": 0, "a": [0, 0, 0, 0], "b": [0, 1, 2, 3]},
                        {"window": 2, "a": [2, 2, 2], "b": [0, 1, 2]}]
    assert columns.topic.dropped == 1 == stats.messages_dropped["/c"]


@pytest.mark.parametrize("in_process", [False, True])
def test_a_row_of_the_wrong_length_fails_the_recording_naming_the_fields(tmp_path, in_process):
    rec = Recorder(tmp_path / "bad.mcap", wait_when_full=True,
                   options=RecordingOptions(in_process=in_process))
    rec.topic("/flat", FLAT, encoding="cdr").log(1, (1.0, 2.0))
    with pytest.raises(HilError, match=r"a row of 2 value\(s\) for a topic of 9 field\(s\) "
                                       r"\(t_s, narrow, count"):
        rec.close()


def test_the_compiled_cdr_encoder_writes_the_bytes_of_the_field_by_field_one():
    """The encoder's precompiled head and one-call sequences against the plain definition,
    on messages with every type, missing fields, numpy arrays and scalars, arrays of the
    standard library, integer fields given floats and bools, and values that do not fit."""
    from array import array

    import numpy as np

    from hil.core.recording.cdr import CdrEncoder, CdrError, fields_of

    encoder = CdrEncoder(fields_of(FLAT))
    rng = np.random.default_rng(7)
    for k in range(300):
        message = _message(k)
        message["samples_mA"] = rng.normal(size=k % 5) if k % 2 else \
            array("d", message["samples_mA"]) if k % 3 else message["samples_mA"]
        message["counts"] = np.arange(k % 4, dtype=np.int64) if k % 2 else \
            [float(c) for c in range(k % 4)]
        if k % 4 == 1:  # integer fields given floats, a bool and numpy scalars
            message.update(word=float(k % 65536), small=k % 2 == 0, count=np.int64(k),
                           t_s=np.float32(k / 7))
        for name in list(message)[k % 9:k % 9 + k % 3]:
            del message[name]
        assert encoder.encode(message) == encoder.encode_by_field(message)
    with pytest.raises(CdrError, match="field 'word': 70000 does not fit uint16"):
        encoder.encode({"word": 70000})
    with pytest.raises(CdrError, match="field 'counts': 3000000000 does not fit int32"):
        encoder.encode({"counts": [1, 3_000_000_000]})


def test_the_kept_strings_and_sequence_structs_write_the_field_by_field_bytes():
    """A string right after the head is written from the bytes kept for its value, the
    structs of a numeric sequence are kept per length: past how many of each are kept, with
    a head of every alignment before the string, strings that are not ``str`` and a string
    alone after the head (written without a buffer), the bytes are the plain definition's."""
    from hil.core.recording.cdr import LENGTHS_KEPT, STRINGS_KEPT, CdrEncoder, Field

    heads = ([], [Field("flag", "bool")], [Field("t_s", "float64"), Field("b", "uint8")],
             [Field("w", "uint16")], [Field("x", "float32"), Field("n", "int8")])
    tails = ([], [Field("y", "float32", sequence=True)],
             [Field("q", "float64", sequence=True), Field("tag", "string")])
    for head in heads:
        for tail in tails:
            encoder = CdrEncoder([*head, Field("path", "string"), *tail])
            for k in range(2 * STRINGS_KEPT + 3):
                path = (None, 7, "\u00fc" * (k % 5), f"qp{k}", "explicit")[k % 5]
                message = {"path": path, "y": [k / 3] * (k % (LENGTHS_KEPT + 5)),
                           "q": [k * 0.5] * (k % 3), "tag": "t" * (k % 4),
                           **{f.name: k % 2 for f in head}}
                assert encoder.encode(message) == encoder.encode_by_field(message), \
                    (head, tail, message)


def test_missing_fields_are_written_as_zero_and_extra_fields_are_not(tmp_path):
    path = tmp_path / "partial.mcap"
    with Recorder(path) as rec:
        rec.topic("/flat", FLAT, encoding="cdr").log(1, {"count": 7, "not_in_schema": 1})
    [(_, message)] = read_session(path).topic("/flat")
    assert message["count"] == 7 and message["t_s"] == 0.0 and message["path"] == ""
    assert message["samples_mA"] == [] and "not_in_schema" not in message


def test_encoding_choice_per_topic(tmp_path):
    options = RecordingOptions(high_rate_encoding="cdr", topic_encodings={"/slow": "cdr",
                                                                          "/fast2": "json"})
    path = tmp_path / "choice.mcap"
    with Recorder(path, options=options) as rec:
        for name, high_rate in (("/fast", True), ("/fast2", True), ("/slow", False),
                                ("/plain", False), ("/nested", True)):
            schema = NESTED if name == "/nested" else FLAT
            rec.topic(name, schema, high_rate=high_rate).log(1, {"t_s": 1.0})
    encodings = read_session(path).encodings
    assert encodings == {"/events": "json", "/fast": "cdr", "/fast2": "json", "/slow": "cdr",
                         "/plain": "json", "/nested": "json"}  # nested: no flat CDR, so JSON


def test_cdr_for_a_nested_topic_by_name_and_unknown_encodings_are_refused(tmp_path):
    with Recorder(tmp_path / "r.mcap") as rec:
        with pytest.raises(HilError, match="/nested: cannot be recorded as CDR"):
            rec.topic("/nested", NESTED, encoding="cdr")
        with pytest.raises(HilError, match="'xml' is not one of json, cdr"):
            rec.topic("/x", FLAT, encoding="xml")
    with pytest.raises(HilError, match="split duration must be > 0"):
        RecordingOptions(split_duration_s=0)


def _record_split(path, options, seconds: float, rate_hz: int = 1000):
    rec = Recorder(path, options=options, wait_when_full=True)
    rec.metadata("session", {"kind": "test"})
    rec.attachment("config.toml", b"a = 1\n", "application/toml")
    topic = rec.topic("/seq", FLAT, high_rate=True)
    for k in range(int(seconds * rate_hz)):
        topic.log(k * 1_000_000_000 // rate_hz, {"count": k, "path": "x" * 30})
    rec.metadata("kpis", {"json": "{\"done\": true}"})
    return rec.close()


def test_split_by_duration_writes_complete_files_read_back_as_one_session(tmp_path):
    path = tmp_path / "run.mcap"
    stats = _record_split(path, RecordingOptions(split_duration_s=1.0), seconds=3.5)
    names = [os.path.basename(f) for f in stats.files]
    assert names == ["run_000.mcap", "run_001.mcap", "run_002.mcap", "run_003.mcap"]
    assert not path.exists()
    for name in stats.files:  # each file complete, indexed, with metadata and config
        with open(name, "rb") as f:
            reader = make_reader(f)
            times = [m.log_time for _, _, m in reader.iter_messages(topics=["/seq"])]
            assert times and times[-1] - times[0] < 1_000_000_000
            assert {m.name for m in reader.iter_metadata()} >= {"session"}
            assert [a.name for a in reader.iter_attachments()] == ["config.toml"]
    for spelled in (path, stats.files[0], tmp_path):  # the unsplit name, the first file, folder
        data = read_session(spelled)
        assert [m["count"] for _, m in data.topic("/seq")] == list(range(3500))
        assert data.metadata["kpis"] == {"json": "{\"done\": true}"}
        assert data.files == stats.files and not data.recovered


@pytest.mark.slow
def test_split_by_size(tmp_path):
    path = tmp_path / "big.mcap"
    stats = _record_split(path, RecordingOptions(split_size_mb=0.05), seconds=20, rate_hz=2000)
    assert len(stats.files) >= 3
    sizes = [os.path.getsize(f) for f in stats.files]
    assert max(sizes[:-1]) < 0.05e6 + (1 << 20)  # rolled at the first check past the size
    assert len(read_session(path).topic("/seq")) == 40_000


CHILD = """
import time
from hil.core.recording.recorder import Recorder, RecordingOptions
rec = Recorder({path!r}, options=RecordingOptions(split_duration_s=0.5))
print("writer", rec.writer_pid, flush=True)
topic = rec.topic("/seq", {{"type": "object", "title": "Seq",
                            "properties": {{"k": {{"type": "integer"}}}}}}, high_rate=True)
t0 = time.monotonic()
k = 0
while True:
    target = t0 + k / 2000
    while time.monotonic() < target:
        time.sleep(0.0002)
    topic.log(int((target - t0) * 1e9), {{"k": k}})
    rec.flush_if_due()
    if k % 200 == 0:
        print(k, flush=True)
    k += 1
"""


@pytest.mark.slow
def test_sigkill_during_a_split_run_keeps_every_file(tmp_path, run_python):
    path = tmp_path / "kill.mcap"
    child = run_python(CHILD.format(path=str(path)))
    try:
        head = child.stdout.readline().split()
        assert head[0] == "writer", child.stderr.read()
        last = 0
        start = time.monotonic()
        while time.monotonic() - start < 2.2:
            line = child.stdout.readline()
            assert line, child.stderr.read()
            last = int(line)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=10)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        try:
            os.kill(int(head[1]), 0)
        except ProcessLookupError:
            break
        time.sleep(0.02)
    files = session_files(path)
    assert len(files) >= 4
    for name in files:  # every file of the series finished and indexed, the last one too
        with open(name, "rb") as f:
            assert sum(1 for _ in make_reader(f).iter_messages()) > 0
    data = read_session(path)
    ks = [m["k"] for _, m in data.topic("/seq")]
    assert ks == list(range(len(ks))) and last - len(ks) <= 100  # at most 50 ms lost
    assert not data.recovered and "without closing" in data.metadata["recorder"]["ended"]


def test_numpy_arrays_in_messages_arrive_as_their_values(tmp_path):
    """Arrays cross to the writer process as raw bytes: strided views, int and float32
    arrays, 0-d values and object arrays come out as the values they held, in JSON and CDR."""
    import numpy as np

    path = tmp_path / "arrays.mcap"
    rec = Recorder(path, wait_when_full=True)
    flat = rec.topic("/flat", FLAT, encoding="cdr")
    free = rec.topic("/free", {"type": "object"})
    samples = np.arange(12.0) * 0.25
    flat.log(1, {"t_s": np.float64(0.5), "samples_mA": samples[::3],
                 "counts": np.array([3, -4], dtype=np.int16)})
    free.log(2, {"grid": np.arange(6, dtype=np.float32).reshape(2, 3) / 4,
                 "mixed": np.array([1, "a"], dtype=object), "scalar": np.array(7)})
    rec.close()

    data = read_session(path)
    [(_, cdr)] = list(data.topic("/flat"))
    assert cdr["samples_mA"] == [0.0, 0.75, 1.5, 2.25] and cdr["counts"] == [3, -4]
    assert cdr["t_s"] == 0.5
    [(_, free_message)] = list(data.topic("/free"))
    assert free_message == {"grid": [[0.0, 0.25, 0.5], [0.75, 1.0, 1.25]],
                            "mixed": [1, "a"], "scalar": 7}


def _session_records(k0: int, k1: int) -> list[tuple]:
    """Records of the stream as the recorder hands them over: messages as dicts, as rows and
    as a topic group's rows, on a CDR and a JSON topic, with metadata among them; and a
    column topic's rows, a message of them every 50 (every 150th's rows let go)."""
    names = list(FLAT["properties"])
    records: list[tuple] = []
    for k in range(k0, k1):
        row = tuple(_message(k).get(name) for name in names)
        records += [(1, k * 500_000, row), (2, k * 500_000, _message(k)),
                    ((1, 2), k * 500_000 + 1, (row, row)), ("row", 3, (k / 2, -k))]
        if k % 97 == 0:
            records.append(("metadata", f"m{k}", {"k": str(k)}))
        if k % 50 == 49:
            fields = None if k % 150 == 149 else {"window": k}
            records.append(("message", 3, k * 500_000 + 2, fields, ("a", "b")))
    return records


def test_a_batch_of_records_writes_what_they_write_one_by_one(tmp_path):
    """SessionWriter.apply_all (how the writer process and the in-process writer apply a
    hand-over) against apply record by record: the same messages, bytes, times and sequence
    numbers, chunk for chunk."""
    from hil.core.recording.writer import SessionWriter, finish, open_series

    topics = [("topic", 1, "/flat", FLAT, "cdr"), ("topic", 2, "/json", FLAT, "json"),
              ("topic", 3, "/columns", COLUMNS, "cdr")]
    files = {}
    for form in ("one by one", "batch"):
        files[form] = str(tmp_path / f"{form}.mcap")
        writer = SessionWriter(open_series({"path": files[form], "chunk_span_s": 0.05}))
        for at in range(0, 900, 300):
            records = topics + _session_records(at, at + 300) if at == 0 else \
                _session_records(at, at + 300)
            if form == "batch":
                writer.apply_all(records)
                assert writer.applied == len(records)
            else:
                for record in records:
                    writer.apply(record)
        finish(writer, "")
    for topic, count in (("/flat", 1800), ("/json", 1800), ("/columns", 12)):
        with open(files["one by one"], "rb") as a, open(files["batch"], "rb") as b:
            alone, batch = ([(m.log_time, m.sequence, m.data) for _, _, m in
                             make_reader(f).iter_messages(topics=[topic])] for f in (a, b))
        assert len(alone) == count and batch == alone
    columns = [m for _, m in read_session(files["batch"]).topic("/columns")]
    assert [m["window"] for m in columns[:2]] == [49, 99]
    assert columns[1]["a"] == [k / 2 for k in range(50, 100)] and columns[1]["b"][-1] == -99
    summaries = [make_reader(open(files[form], "rb")).get_summary()  # noqa: SIM115
                 for form in files]
    assert [len(s.chunk_indexes) for s in summaries] == [len(summaries[0].chunk_indexes)] * 2
    assert len(summaries[0].chunk_indexes) > 3


def test_a_bad_row_in_a_batch_fails_it_after_writing_the_records_before_it(tmp_path):
    """As apply one record at a time: the messages before the one that cannot be encoded are
    in the file, and ``applied`` counts the records they came in."""
    from hil.core.recording.writer import SessionWriter, finish, open_series

    path = str(tmp_path / "bad.mcap")
    writer = SessionWriter(open_series({"path": path}))
    records = [("topic", 1, "/flat", FLAT, "cdr"), ("topic", 2, "/json", FLAT, "json"),
               *[record for record in _session_records(0, 2) if record[0] != "row"]]
    # k = 0's messages and metadata at 2-5, k = 1's at 6-8
    records.insert(7, (1, 1, (1.0, 2.0)))
    with pytest.raises(ValueError, match=r"a row of 2 value\(s\) for a topic of 9 field\(s\)"):
        writer.apply_all(records)
    assert writer.applied == 7
    finish(writer, "")
    assert read_session(path).topic_counts == {"/flat": 3, "/json": 2}
