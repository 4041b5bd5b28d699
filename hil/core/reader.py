"""Read a session file, finished or truncated (e.g. after SIGKILL or a power cut).

The stock indexed reader needs the summary at the end of the file and raises on a truncated
one. :func:`read_session` walks the file record by record instead (``StreamReader``) and keeps
every complete chunk; ``recovered`` tells whether the file had to be salvaged and
``lost_bytes`` how much of its tail was unreadable.
"""

from __future__ import annotations

import json
import os
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from mcap.exceptions import McapError
from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from hil.core.errors import SessionFileError


@dataclass
class SessionData:
    """Everything readable from one session file, messages decoded from JSON."""

    path: str
    messages: dict[str, list[tuple[int, Any]]] = field(default_factory=dict)
    schemas: dict[str, dict[str, Any]] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    recovered: bool = False
    lost_bytes: int = 0
    error: str = ""

    @property
    def topic_counts(self) -> dict[str, int]:
        return {topic: len(msgs) for topic, msgs in sorted(self.messages.items())}

    def time_range_ns(self) -> tuple[int, int] | None:
        stamps = [t for msgs in self.messages.values() for t, _ in msgs[:1] + msgs[-1:]]
        return (min(stamps), max(stamps)) if stamps else None

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


def read_session(path: str | os.PathLike[str]) -> SessionData:
    """Read every complete record of ``path``; never raises on a truncated tail."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise SessionFileError(f"{path}: no such session file")
    size = os.path.getsize(path)
    data = SessionData(path=path)
    schemas: dict[int, dict[str, Any]] = {}
    channels: dict[int, tuple[str, int]] = {}
    raw: dict[str, list[tuple[int, bytes]]] = defaultdict(list)
    complete_until = 0
    finished = False
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, record_size_limit=size + 1).records:
                if isinstance(record, Schema):
                    schemas[record.id] = _parse_schema(record)
                elif isinstance(record, Channel):
                    channels[record.id] = (record.topic, record.schema_id)
                    data.schemas.setdefault(record.topic, schemas.get(record.schema_id, {}))
                    raw.setdefault(record.topic, [])
                elif isinstance(record, Message):
                    topic = channels.get(record.channel_id, (f"<channel {record.channel_id}>",))[0]
                    raw[topic].append((record.log_time, record.data))
                elif isinstance(record, Metadata):
                    data.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Attachment):
                    data.attachments[record.name] = bytes(record.data)
                elif isinstance(record, Footer):
                    finished = True
                complete_until = f.tell()
        except (McapError, EOFError, ValueError, OSError) as exc:
            data.error = f"{type(exc).__name__}: {exc}".strip(": ")
        except Exception as exc:  # corrupt chunk payloads raise from zstd/struct internals
            data.error = f"{type(exc).__name__}: {exc}"
    if complete_until == 0 and not finished:
        raise SessionFileError(f"{path}: not an MCAP session file ({data.error or 'empty'})")
    data.recovered = not finished
    data.lost_bytes = size - complete_until if not finished else 0
    for topic, items in raw.items():
        items.sort(key=lambda item: item[0])
        data.messages[topic] = [(t, _decode(payload)) for t, payload in items]
    return data


def _parse_schema(record: Schema) -> dict[str, Any]:
    try:
        return json.loads(record.data) if record.encoding == "jsonschema" else {}
    except ValueError:
        return {}


def _decode(payload: bytes) -> Any:
    try:
        return json.loads(payload)
    except ValueError:
        return {"_undecodable": len(payload)}
