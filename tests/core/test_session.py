import json
import time

import numpy as np
import pytest
from mcap.reader import make_reader

from hil.core.clock import SimClock
from hil.core.loop import FunctionTask
from hil.core.recording.reader import read_session
from hil.core.recording.recorder import Recorder
from hil.core.session import Session
from hil.errors import RecordingError

SCHEMA = {
    "type": "object",
    "title": "test.Sample",
    "properties": {"k": {"type": "integer"}, "x": {"type": "number"}, "v": {"type": "array"}},
}


def test_logged_messages_read_back_identically_with_schemas_metadata_and_config(tmp_path):
    path = tmp_path / "s.mcap"
    config = {"bench": {"port": 5020, "relays": ["M1", "M2"]}}
    session = Session(str(path), SimClock(), 0.01, kind="test", config=config,
                      config_text="[bench]\nport = 5020\n", handle_signals=False)
    samples = session.topic("/test/samples", SCHEMA)
    nested = session.topic("/test/nested", {"type": "object", "title": "test.Nested"})
    sent = []

    def log(t_ns):
        k = len(sent)
        msg = {"k": k, "x": k * 0.25 - 3.0, "v": [k, -k, 0.5]}
        sent.append((t_ns, msg))
        samples.log(t_ns, msg)
        if k % 10 == 0:
            nested.log(t_ns, {"plan": np.arange(3) * k, "ok": True, "name": f"n{k}", "none": None})

    session.add_task(FunctionTask("log", 1, write=log))
    session.run(max_ticks=250)
    session.close(kpis={"J1_VA": 123.5})

    data = read_session(path)
    assert not data.recovered and data.lost_bytes == 0
    assert data.topic("/test/samples") == sent
    assert data.topic("/test/nested")[3] == (
        300_000_000, {"plan": [0, 30, 60], "ok": True, "name": "n30", "none": None}
    )
    # every channel carries a schema Foxglove decodes without a plug-in: JSON with a JSON
    # Schema, or (the high-rate loop timing) CDR with a ros2msg schema
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    for channel in summary.channels.values():
        schema = summary.schemas[channel.schema_id]
        if channel.topic == "/loop/log/timing":
            assert (channel.message_encoding, schema.encoding) == ("cdr", "ros2msg")
            continue
        assert channel.message_encoding == "json"
        assert schema.encoding == "jsonschema" and json.loads(schema.data)["type"] == "object"
    topics = {c.topic for c in summary.channels.values()}
    assert {"/test/samples", "/test/nested", "/events", "/loop/log/timing"} <= topics
    assert data.metadata["session"]["clock"] == "sim"
    assert data.metadata["session"]["kind"] == "test"
    assert json.loads(data.metadata["config"]["json"]) == config
    assert "numpy" in data.metadata["versions"] and "mcap" in data.metadata["versions"]
    assert data.attachments["config.toml"] == b"[bench]\nport = 5020\n"
    assert json.loads(data.metadata["kpis"]["json"]) == {"J1_VA": 123.5}
    kinds = [m["kind"] for _, m in data.topic("/events")]
    assert kinds[0] == "session.start" and kinds[-1] == "session.stop"


def test_every_session_records_the_installed_versions_read_once_a_process(tmp_path,
                                                                         monkeypatch):
    from importlib import metadata

    from hil.core import session as session_module

    session_module._installed_versions.cache_clear()
    reads: list[str] = []
    installed = metadata.version

    def version(name: str) -> str:
        reads.append(name)
        return installed(name)

    monkeypatch.setattr(session_module.importlib_metadata, "version", version)
    recorded = []
    for name in ("a", "b"):
        session = Session(str(tmp_path / f"{name}.mcap"), SimClock(), 0.01, kind="test",
                          handle_signals=False)
        session.run(max_ticks=2)
        session.close()
        recorded.append(read_session(tmp_path / f"{name}.mcap").metadata["versions"])
    assert recorded[0] == recorded[1]
    assert recorded[0]["numpy"] == np.__version__ and recorded[0]["mcap"] == installed("mcap")
    # each package's metadata file parsed by the first session alone
    assert sorted(reads) == sorted(session_module.VERSIONED_PACKAGES)
    session_module.package_versions()["numpy"] = "changed"  # a caller's copy, not the cache
    assert session_module.package_versions()["numpy"] == np.__version__


def test_topic_as_numpy_arrays(tmp_path):
    path = tmp_path / "a.mcap"
    with Recorder(path) as rec:
        topic = rec.topic("/p", SCHEMA)
        for k in range(50):
            topic.log(k * 10_000_000, {"k": k, "x": k / 2, "v": [k, 2 * k]})
    arrays = read_session(path).arrays("/p")
    assert arrays["log_time_ns"].dtype == np.int64
    np.testing.assert_array_equal(arrays["k"], np.arange(50))
    np.testing.assert_allclose(arrays["x"], np.arange(50) / 2)
    assert arrays["v"].shape == (50, 2) and arrays["v"][7].tolist() == [7, 14]


def test_full_queue_drops_are_counted_and_recorded_in_events(tmp_path):
    path = tmp_path / "d.mcap"
    # hand over every message, and refuse any while a byte waits: the 1 MiB pipe holds about
    # 100 of these 10 kB messages, so most of a burst this fast must be dropped and counted
    rec = Recorder(path, batch_size=1, max_backlog_bytes=1)
    topic = rec.topic("/burst", SCHEMA)
    accepted = sum(topic.log(k, {"k": k, "pad": "x" * 10_000}) for k in range(2000))
    stats = rec.close()
    data = read_session(path)
    assert topic.dropped > 0
    assert accepted + topic.dropped == 2000
    assert len(data.topic("/burst")) == accepted
    assert stats.messages_dropped == {"/burst": topic.dropped}
    drops = [m for _, m in data.topic("/events") if m["kind"] == "recorder.dropped"]
    assert sum(m["data"]["dropped"] for m in drops) == topic.dropped
    assert json.loads(data.metadata["recorder"]["dropped"]) == {"/burst": topic.dropped}


def test_lockstep_session_waits_for_the_writer_instead_of_dropping(tmp_path):
    path = tmp_path / "w.mcap"
    session = Session(str(path), SimClock(), 0.01, kind="test", handle_signals=False)
    session.recorder.batch_size = 1  # hand over every message ...
    session.recorder.max_backlog_bytes = 1  # ... and never hold a backlog: the pipe fills
    topic = session.topic("/burst", SCHEMA)
    pad = "x" * 2000
    session.add_task(FunctionTask("log", 1, write=lambda t: [topic.log(t, {"k": k, "pad": pad})
                                                                for k in range(20)]))
    session.run(max_ticks=300)
    stats = session.close()
    assert topic.dropped == 0 and stats.messages_dropped == {}
    assert len(read_session(path).topic("/burst")) == 6000


def test_topics_registered_while_the_writer_runs_are_never_lost(tmp_path):
    # each topic is logged to right after registration, racing the writer's setup step
    path = tmp_path / "race.mcap"
    rec = Recorder(path)
    for k in range(300):
        rec.topic(f"/t{k}", SCHEMA).log(k, {"k": k})
        if k % 50 == 0:
            time.sleep(0.006)  # let the writer start cycles in between
    stats = rec.close()
    assert stats.messages_written == 300 and stats.messages_dropped == {}
    data = read_session(path)
    assert all(data.topic(f"/t{k}") == [(k, {"k": k})] for k in range(300))


def test_a_failing_writer_is_reported_at_close_not_silent(tmp_path):
    path = tmp_path / "fail.mcap"
    rec = Recorder(path)
    topic = rec.topic("/x", SCHEMA)
    topic.log(1, {"k": 1})
    topic.log(2, {"not json": object()})  # cannot be encoded: the writer fails on it
    rec.flush()
    deadline = time.monotonic() + 10
    while rec._process.poll() is None and time.monotonic() < deadline:  # the writer gives up
        time.sleep(0.01)
    topic.log(3, {"k": 3})  # handed to a writer that is gone: lost, and counted
    with pytest.raises(RecordingError, match=r"TypeError: cannot record a object as JSON"):
        rec.close()
    assert topic.dropped >= 1
    assert read_session(path).topic("/x") == [(1, {"k": 1})]
