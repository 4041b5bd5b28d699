"""Read a session: one MCAP file or a split series, finished, truncated or damaged.

:func:`read_session` walks each file record by record (:mod:`hil.core.recording.mcap_walk`),
checks chunk CRCs, keeps every readable message, and says what it could not read: ``damage``
lists each unreadable part (truncated tail, damaged chunk, damaged summary) with its offset,
bytes and, where the file's indexes tell, the messages lost. ``recovered`` is true when a file
was not finished (no footer: the writer was killed) or anything was damaged.

Messages are decoded by their channel's encoding: ``json``, or ``cdr`` with a ``ros2msg``
schema (:mod:`hil.core.recording.cdr`). A split series (``<stem>_000.mcap``,
``<stem>_001.mcap``...) is read as one session from its folder, its first file or its unsplit
name.
"""

from __future__ import annotations

import glob
import json
import mmap
import os
import re
from collections import defaultdict
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from mcap.records import Attachment, Channel, Message, Metadata, Schema

from hil.core.recording.cdr import CdrDecoder, CdrError, parse_ros2msg
from hil.core.recording.mcap_walk import Damage, Walk, walk
from hil.errors import SessionFileError

_SERIES = re.compile(r"^(?P<stem>.*)_(?P<index>\d{3,})\.mcap$")


class Topics(Mapping[str, list[tuple[int, Any]]]):
    """A session's messages by topic, ``(log_time_ns, message)`` pairs in time order. Each
    topic is decoded when it is first read, so a command that reads two topics of a long
    session decodes only those; counts and time spans come without decoding."""

    def __init__(self, raw: dict[str, list[tuple[int, bytes]]] | None = None,
                 decoders: dict[str, Callable[[bytes], Any]] | None = None) -> None:
        self._raw = raw or {}
        self._decoders = decoders or {}
        self._decoded: dict[str, list[tuple[int, Any]]] = {}
        self._counts = {topic: len(items) for topic, items in self._raw.items()}
        self._spans = {topic: (items[0][0], items[-1][0])
                       for topic, items in self._raw.items() if items}

    def __getitem__(self, topic: str) -> list[tuple[int, Any]]:
        decoded = self._decoded.get(topic)
        if decoded is None:
            items = self._raw.pop(topic)  # the payloads, no longer needed once decoded
            decode = self._decoders.get(topic, _decode_json)
            decoded = self._decoded[topic] = [(t, decode(payload)) for t, payload in items]
        return decoded

    def __iter__(self) -> Iterator[str]:
        return iter(self._counts)

    def __len__(self) -> int:
        return len(self._counts)

    def __contains__(self, topic: object) -> bool:
        return topic in self._counts

    def count(self, topic: str) -> int:
        """The number of messages of ``topic`` (0 when absent), without decoding them."""
        return self._counts.get(topic, 0)

    def span_ns(self, topic: str) -> tuple[int, int] | None:
        """The first and last log time of ``topic``, without decoding it."""
        return self._spans.get(topic)


@dataclass
class SessionData:
    """Everything readable from one session (file or series), messages decoded as read."""

    path: str
    messages: Topics = field(default_factory=Topics)
    schemas: dict[str, dict[str, Any]] = field(default_factory=dict)
    encodings: dict[str, str] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    files: list[str] = field(default_factory=list)
    damage: list[Damage] = field(default_factory=list)
    recovered: bool = False
    lost_bytes: int = 0
    error: str = ""
    #: messages the files' statistics say they hold (None: a file without them)
    expected_messages: int | None = 0

    @property
    def lost_messages(self) -> int | None:
        """Messages known lost to damage: each damage's count, or where one does not say,
        what the files' statistics hold beyond what was read; None when neither tells."""
        counts = [d.messages for d in self.damage if d.kind not in ("summary", "trailing")]
        if all(c is not None for c in counts):
            return sum(c for c in counts if c is not None)
        if self.expected_messages is None:
            return None
        return max(0, self.expected_messages - sum(self.topic_counts.values()))

    @property
    def topic_counts(self) -> dict[str, int]:
        return {topic: self.messages.count(topic) for topic in sorted(self.messages)}

    def time_range_ns(self) -> tuple[int, int] | None:
        spans = [span for topic in self.messages
                 if (span := self.messages.span_ns(topic)) is not None]
        return (min(s[0] for s in spans), max(s[1] for s in spans)) if spans else None

    def duration_s(self) -> float:
        span = self.time_range_ns()
        return (span[1] - span[0]) / 1e9 if span else 0.0

    def topic(self, name: str) -> list[tuple[int, Any]]:
        """(log_time_ns, message) pairs of one topic; empty when absent."""
        return self.messages.get(name, [])

    def arrays(self, name: str) -> dict[str, np.ndarray]:
        """A topic as numpy arrays: ``log_time_ns`` plus one array per message field.

        Scalar fields become 1-D arrays; fixed-length list fields become 2-D arrays; fields
        whose shape varies between messages become object arrays.
        """
        msgs = self.topic(name)
        out: dict[str, np.ndarray] = {
            "log_time_ns": np.array([t for t, _ in msgs], dtype=np.int64)
        }
        if not msgs or not isinstance(msgs[0][1], dict):
            return out
        keys: list[str] = []
        for _, message in msgs:
            keys.extend(k for k in message if k not in keys)
        for key in keys:
            values = [message.get(key) for _, message in msgs]
            try:
                array = np.array(values)
            except ValueError:  # ragged lists
                array = np.empty(len(values), dtype=object)
                array[:] = values
            out[key] = array
        return out


def session_files(path: str | os.PathLike[str]) -> list[str]:
    """The file(s) of the session at ``path``: a file, a split series, or a folder of one."""
    path = os.fspath(path)
    if os.path.isdir(path):
        files = sorted(glob.glob(os.path.join(glob.escape(path), "*.mcap")))
        if not files:
            raise SessionFileError(f"{path}: no .mcap session file in this folder")
        stems = {m.group("stem") for f in files if (m := _SERIES.match(f))}
        if len(stems) > 1 or (stems and len(files) != sum(1 for f in files if _SERIES.match(f))):
            raise SessionFileError(f"{path}: holds more than one session; name one file")
        return files
    match = _SERIES.match(path)
    if match and os.path.isfile(path):
        return _series(match.group("stem")) or [path]
    if os.path.isfile(path):
        return [path]
    stem, _ = os.path.splitext(path)
    series = _series(stem)
    if series:
        return series
    raise SessionFileError(f"{path}: no such session file")


def _series(stem: str) -> list[str]:
    files = []
    index = 0
    while os.path.isfile(name := f"{stem}_{index:03d}.mcap"):
        files.append(name)
        index += 1
    return files


def read_session(path: str | os.PathLike[str]) -> SessionData:
    """Read every readable record of the session at ``path``; never raises on damage."""
    files = session_files(path)
    data = SessionData(path=os.fspath(path), files=files)
    raw: dict[str, list[tuple[int, bytes]]] = defaultdict(list)
    decoders: dict[str, Callable[[bytes], Any]] = {}
    for name in files:
        _read_file(name, data, raw, decoders)
    for items in raw.values():
        items.sort(key=lambda item: item[0])
    data.messages = Topics(dict(raw), decoders)
    return data


def _read_file(path: str, data: SessionData, raw: dict[str, list[tuple[int, bytes]]],
               decoders: dict[str, Callable[[bytes], Any]]) -> None:
    size = os.path.getsize(path)
    if size == 0:
        raise SessionFileError(f"{path}: not an MCAP session file (empty)")
    state = Walk()
    schemas: dict[int, Schema] = {}
    channels: dict[int, str] = {}
    by_channel: dict[int, list[tuple[int, bytes]]] = defaultdict(list)
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as view:
        try:
            for record in walk(view, state):
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record.topic
                    if record.topic not in decoders:
                        _register(data, decoders, record, schemas.get(record.schema_id))
                    raw.setdefault(record.topic, [])
                elif isinstance(record, Message):
                    by_channel[record.channel_id].append((record.log_time, record.data))
                elif isinstance(record, Metadata):
                    data.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Attachment):
                    data.attachments[record.name] = bytes(record.data)
        except ValueError as exc:
            raise SessionFileError(f"{path}: {exc}") from None
    # by channel id, once the walk is over: a channel may be known only from the summary
    for channel_id, items in by_channel.items():
        raw[channels.get(channel_id, f"<channel {channel_id}>")].extend(items)
    _account(path, data, state, sum(map(len, by_channel.values())))


def _account(path: str, data: SessionData, state: Walk, seen: int) -> None:
    """Fold one file's damage into the session; count truncated messages where knowable. A
    finished file whose own statistics count other messages than were read lost a record
    nothing else showed (a chunk's opcode changed, say)."""
    damaged_summary = any(d.kind == "summary" for d in state.damage)
    stats = None if damaged_summary else state.statistics
    if stats is not None and state.finished and not state.damage and \
            seen != stats.message_count:
        state.damage.append(Damage(
            "record", 0, 0, messages=max(0, stats.message_count - seen),
            reason=f"its statistics count {stats.message_count} messages, {seen} were read"))
    for damage in state.damage:
        if damage.kind == "truncated" and damage.messages is None and stats is not None:
            damage.messages = max(0, stats.message_count - seen)
        damage.reason = f"{os.path.basename(path)}: {damage.reason}" if damage.reason else \
            os.path.basename(path)
    data.damage.extend(state.damage)
    data.lost_bytes += sum(d.bytes for d in state.damage)
    if stats is None or data.expected_messages is None:
        data.expected_messages = None
    else:
        data.expected_messages += stats.message_count
    if not state.finished or state.damage:
        data.recovered = True
        data.error = data.error or "; ".join(d.reason for d in state.damage) or \
            f"{os.path.basename(path)}: not finished (no footer)"


def _register(data: SessionData, decoders: dict[str, Callable[[bytes], Any]],
              channel: Channel, schema: Schema | None) -> None:
    topic = channel.topic
    data.encodings[topic] = channel.message_encoding
    if schema is not None and schema.encoding == "jsonschema":
        try:
            data.schemas[topic] = json.loads(schema.data)
        except ValueError:
            data.schemas[topic] = {}
    elif schema is not None and schema.encoding == "ros2msg":
        data.schemas[topic] = {"ros2msg": schema.data.decode(errors="replace")}
    if channel.message_encoding == "cdr" and schema is not None:
        try:
            decoders[topic] = _guarded(CdrDecoder(parse_ros2msg(schema.data.decode())).decode)
        except (CdrError, UnicodeDecodeError):
            decoders[topic] = _undecodable
    elif channel.message_encoding != "json":
        decoders[topic] = _undecodable


def _guarded(decode: Callable[[bytes], Any]) -> Callable[[bytes], Any]:
    def safe(payload: bytes) -> Any:
        try:
            return decode(payload)
        except (CdrError, ValueError, IndexError):  # struct.error is a ValueError
            return {"_undecodable": len(payload)}
    return safe


def _decode_json(payload: bytes) -> Any:
    try:
        return json.loads(payload)
    except ValueError:
        return {"_undecodable": len(payload)}


def _undecodable(payload: bytes) -> Any:
    return {"_undecodable": len(payload)}
