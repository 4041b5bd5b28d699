"""A baseline file: a session cut down to what a comparison reads - its metadata (the KPIs,
the session's kind, clock and rate, the configuration) and the chosen signals, each a CDR
topic of just those fields in the session's own wire types, so that values read back exactly.
It is an MCAP session like any other: ``hil compare`` and ``hil report`` read it."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from hil.compare.comparison import series
from hil.core.recording.cdr import CdrEncoder, Field, parse_ros2msg, ros2msg_text
from hil.core.recording.mcap_writer import McapWriter
from hil.core.recording.reader import SessionData, read_session
from hil.errors import UsageError


def write_baseline(session: str | os.PathLike[str], out: str | os.PathLike[str],
                   signals: Sequence[str], every: int = 1) -> int:
    """Write the baseline of ``session`` with ``signals`` (``TOPIC:FIELD``) to ``out``
    (replaced whole, never half-written), keeping every ``every``-th tick of them (a
    comparison then checks the candidate on those ticks); returns its size in bytes."""
    if every < 1:
        raise UsageError(f"every={every}: keep every 1st tick or more sparsely (>= 1)")
    data = read_session(session)
    topics: dict[str, list[str]] = {}
    for name in signals:
        series(data, name, "session")  # the signal is there, and numeric
        topic, _, key = name.rpartition(":")
        topics.setdefault(topic, []).append(key)
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    with open(partial, "wb") as stream:
        writer = McapWriter(stream, zstd_level=19)
        writer.start(library="hil baseline")
        for name, record in data.metadata.items():
            writer.add_metadata(name, record)
        for topic, keys in topics.items():
            fields = _fields(data, topic, keys)
            schema = writer.register_schema(topic.strip("/").replace("/", "_"), "ros2msg",
                                            ros2msg_text(fields).encode())
            channel = writer.register_channel(topic, "cdr", schema)
            encode = CdrEncoder(fields).encode
            for log_time, message in data.topic(topic)[::every]:
                writer.add_message(channel, log_time, encode(message), log_time)
        writer.finish()
    os.replace(partial, path)
    return path.stat().st_size


def _fields(data: SessionData, topic: str, keys: list[str]) -> list[Field]:
    """``keys`` as CDR fields of the types the session recorded them in (float64 for a JSON
    topic), so that every value reads back as it was."""
    recorded = data.schemas.get(topic, {}).get("ros2msg")
    types = {f.name: f.type for f in parse_ros2msg(recorded)} if recorded else {}
    return [Field(key, types.get(key, "float64")) for key in dict.fromkeys(keys)]
