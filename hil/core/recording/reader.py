"""Read a session: one MCAP file or a split series, finished, truncated or damaged.

:func:`read_session` walks each file record by record (:mod:`hil.core.recording.mcap_walk`),
checks chunk CRCs, keeps every readable message, and says what it could not read: ``damage``
lists each unreadable part (truncated tail, damaged chunk, damaged summary) with its offset,
bytes and, where the file's indexes tell, the messages lost. ``recovered`` is true when a file
was not finished (no footer: the writer was killed) or anything was damaged.

Messages are decoded by their channel's encoding: ``json``, or ``cdr`` with a ``ros2msg``
schema (:mod:`hil.core.recording.cdr`), and only when a topic is read. A CDR topic is decoded
field by field over all its messages at once (:mod:`hil.core.recording.cdr_columns`), each
field only when asked for (:meth:`SessionData.arrays`); one with a message its schema does not
describe is decoded message by message. A split series (``<stem>_000.mcap``,
``<stem>_001.mcap``...) is read as one session from its folder, its first file or its unsplit
name.
"""

from __future__ import annotations

import glob
import json
import mmap
import os
import re
import struct
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from mcap.records import Attachment, Channel, Message, Metadata, Schema

from hil.core.recording.cdr import CdrDecoder, CdrError, parse_ros2msg
from hil.core.recording.cdr_columns import CdrColumns, Layout, as_array
from hil.core.recording.chunk_messages import ChunkMessages
from hil.core.recording.mcap_walk import Damage, Walk, walk
from hil.core.recording.message_store import MessageStore, TopicMessages
from hil.errors import SessionFileError

_SERIES = re.compile(r"^(?P<stem>.*)_(?P<index>\d{3,})\.mcap$")


class Columns(Mapping[str, np.ndarray]):
    """A topic as arrays, ``log_time_ns`` first, each field decoded when first read."""

    def __init__(self, log_time_ns: np.ndarray, layout: Layout) -> None:
        self._layout = layout
        self._arrays = {"log_time_ns": log_time_ns}
        self._keys = dict.fromkeys(["log_time_ns", *layout.names])

    def __getitem__(self, key: str) -> np.ndarray:
        array = self._arrays.get(key)
        if array is None:
            if key not in self._keys:
                raise KeyError(key)
            array = self._arrays[key] = self._layout.column(key)
        return array

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys)

    def __len__(self) -> int:
        return len(self._keys)

    def __contains__(self, key: object) -> bool:
        return key in self._keys


class Topics(Mapping[str, list[tuple[int, Any]]]):
    """A session's messages by topic, ``(log_time_ns, message)`` pairs in time order. Each
    topic is decoded when it is first read, so a command that reads two topics of a long
    session decodes only those; counts and time spans come without decoding."""

    def __init__(self, stored: dict[str, TopicMessages] | None = None,
                 buffer: bytes | bytearray = b"",
                 decoders: dict[str, Callable[[bytes], Any]] | None = None,
                 columns: dict[str, CdrColumns] | None = None) -> None:
        self._stored = stored or {}
        self._buffer = buffer
        self._data = np.frombuffer(buffer, dtype=np.uint8)
        self._decoders = decoders or {}
        self._columns = columns or {}
        self._layouts: dict[str, Layout | None] = {}
        self._decoded: dict[str, list[tuple[int, Any]]] = {}
        self._arrays: dict[str, Columns] = {}

    def __getitem__(self, topic: str) -> list[tuple[int, Any]]:
        decoded = self._decoded.get(topic)
        if decoded is None:
            stored = self._stored[topic]
            layout = self.layout(topic)
            if layout is not None:
                messages = layout.messages()
            else:
                decode = self._decoders.get(topic, _decode_json)
                data = memoryview(self._buffer)
                messages = [decode(bytes(data[start:start + size])) for start, size in
                            zip(stored.starts.tolist(), stored.sizes.tolist(), strict=True)]
            decoded = self._decoded[topic] = list(zip(stored.log_times.tolist(), messages,
                                                      strict=True))
        return decoded

    def __iter__(self) -> Iterator[str]:
        return iter(self._stored)

    def __len__(self) -> int:
        return len(self._stored)

    def __contains__(self, topic: object) -> bool:
        return topic in self._stored

    def count(self, topic: str) -> int:
        """The number of messages of ``topic`` (0 when absent), without decoding them."""
        stored = self._stored.get(topic)
        return 0 if stored is None else int(stored.log_times.size)

    def log_times(self, topic: str) -> np.ndarray:
        """The log times of ``topic``'s messages [ns], in order (uint64), without decoding."""
        stored = self._stored.get(topic)
        return np.empty(0, dtype=np.uint64) if stored is None else stored.log_times

    def span_ns(self, topic: str) -> tuple[int, int] | None:
        """The first and last log time of ``topic``, without decoding it."""
        stored = self._stored.get(topic)
        if stored is None or stored.log_times.size == 0:
            return None
        return int(stored.log_times[0]), int(stored.log_times[-1])

    def layout(self, topic: str) -> Layout | None:
        """The fields of a CDR topic placed in each message (None: not a CDR topic, or one
        decoded message by message)."""
        if topic not in self._layouts:
            columns, stored = self._columns.get(topic), self._stored.get(topic)
            self._layouts[topic] = None if columns is None or stored is None else \
                columns.lay_out(self._data, stored.starts, stored.sizes)
        return self._layouts[topic]

    def columns(self, topic: str) -> Columns | None:
        """A CDR topic as arrays decoded field by field (None: not one that can be)."""
        if topic not in self._arrays:
            layout = self.layout(topic)
            if layout is None or layout.count == 0:
                return None
            self._arrays[topic] = Columns(self._stored[topic].log_times.astype(np.int64),
                                          layout)
        return self._arrays[topic]


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

    def arrays(self, name: str) -> Mapping[str, np.ndarray]:
        """A topic as numpy arrays: ``log_time_ns`` plus one array per message field.

        Scalar fields become 1-D arrays; fixed-length list fields become 2-D arrays; fields
        whose shape varies between messages become object arrays. A CDR topic's fields are
        decoded as they are read from the mapping.
        """
        columns = self.messages.columns(name)
        if columns is not None:
            return columns
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
            out[key] = as_array([message.get(key) for _, message in msgs])
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
    store = MessageStore()
    decoders: dict[str, Callable[[bytes], Any]] = {}
    columns: dict[str, CdrColumns] = {}
    for name in files:
        _read_file(name, data, store, decoders, columns)
    data.messages = Topics(store.finish(), store.buffer, decoders, columns)
    return data


def _read_file(path: str, data: SessionData, store: MessageStore,
               decoders: dict[str, Callable[[bytes], Any]],
               columns: dict[str, CdrColumns]) -> None:
    size = os.path.getsize(path)
    if size == 0:
        raise SessionFileError(f"{path}: not an MCAP session file (empty)")
    state = Walk()
    schemas: dict[int, Schema] = {}
    channels: dict[int, str] = {}
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as view:
        try:
            for record in walk(view, state):
                if isinstance(record, ChunkMessages):
                    store.add_chunk(record)
                elif isinstance(record, Message):
                    store.add_message(record.channel_id, record.log_time, record.data)
                elif isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record.topic
                    if record.topic not in decoders:
                        _register(data, decoders, columns, record,
                                  schemas.get(record.schema_id))
                    store.declare(record.topic)
                elif isinstance(record, Metadata):
                    data.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Attachment):
                    data.attachments[record.name] = bytes(record.data)
        except ValueError as exc:
            raise SessionFileError(f"{path}: {exc}") from None
    # by channel id, once the walk is over: a channel may be known only from the summary
    _account(path, data, state, store.end_file(channels))


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
              columns: dict[str, CdrColumns], channel: Channel, schema: Schema | None) -> None:
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
            fields = parse_ros2msg(schema.data.decode())
        except (CdrError, UnicodeDecodeError):
            decoders[topic] = _undecodable
        else:
            decoders[topic] = _guarded(CdrDecoder(fields).decode)
            columns[topic] = CdrColumns(fields)
    elif channel.message_encoding != "json":
        decoders[topic] = _undecodable


def _guarded(decode: Callable[[bytes], Any]) -> Callable[[bytes], Any]:
    def safe(payload: bytes) -> Any:
        try:
            return decode(payload)
        except (CdrError, ValueError, IndexError, struct.error):  # cut short: struct.error
            return {"_undecodable": len(payload)}
    return safe


def _decode_json(payload: bytes) -> Any:
    try:
        return json.loads(payload)
    except ValueError:
        return {"_undecodable": len(payload)}


def _undecodable(payload: bytes) -> Any:
    return {"_undecodable": len(payload)}
