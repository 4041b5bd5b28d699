"""Stream a recorded session through a :class:`~hil.core.recording.live.LiveSink`, as if it ran
now."""

from __future__ import annotations

import heapq
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from hil.core.recording.cdr import CdrError, parse_ros2msg
from hil.core.recording.live import LiveSink
from hil.core.recording.reader import SessionData

_JSON_TYPES = {"bool": "boolean", "string": "string"}


def json_schema_of(topic: str, schema: dict[str, Any]) -> dict[str, Any]:
    """The JSON Schema of a topic as read from a file: as recorded for JSON topics, derived
    from the ros2msg fields for CDR topics (the file keeps only those)."""
    if "ros2msg" not in schema:
        return schema
    try:
        fields = parse_ros2msg(schema["ros2msg"])
    except CdrError:
        return {}
    properties: dict[str, Any] = {}
    for field in fields:
        kind = _JSON_TYPES.get(field.type) or (
            "number" if field.type.startswith("float") else "integer")
        prop: dict[str, Any] = {"type": kind}
        properties[field.name] = {"type": "array", "items": prop} if field.sequence else prop
    title = "hil." + "".join(p.capitalize() for p in topic.strip("/").replace("/", "_").split("_"))
    return {"type": "object", "title": title, "properties": properties}


@dataclass
class ReplayStats:
    messages: int
    session_s: float
    wall_s: float


def merged(data: SessionData) -> Iterator[tuple[int, str, Any]]:
    """Every message of the session in log-time order: ``(t_ns, topic, message)``."""
    def stream(topic: str, msgs: list[tuple[int, Any]]) -> Iterator[tuple[int, str, Any]]:
        return ((t, topic, m) for t, m in msgs)

    streams = [stream(topic, msgs) for topic, msgs in data.messages.items()]
    return heapq.merge(*streams, key=lambda item: item[0])


def advertise(data: SessionData, sink: LiveSink) -> None:
    """Advertise every topic of ``data`` on ``sink`` (keyed by topic name)."""
    for topic in sorted(data.messages):
        sink.add_topic(topic, topic, json_schema_of(topic, data.schemas.get(topic, {})))


def replay(data: SessionData, sink: LiveSink, speed: float = 1.0,
           stop: Callable[[], bool] = lambda: False) -> ReplayStats:
    """Serve ``data`` (advertised) on ``sink`` at ``speed`` x real time (0: at once)."""
    start = time.monotonic()
    first = last = None
    count = 0
    for t_ns, topic, message in merged(data):
        if stop():
            break
        if first is None:
            first = t_ns
        if speed > 0:
            delay = start + (t_ns - first) / 1e9 / speed - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        sink.log(topic, t_ns, message)
        last = t_ns
        count += 1
    session_s = (last - first) / 1e9 if first is not None and last is not None else 0.0
    return ReplayStats(count, session_s, time.monotonic() - start)
