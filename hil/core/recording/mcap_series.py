"""One session written as an MCAP file, or as a numbered series of them (splitting).

Without splitting the session is the one file at ``path``. With ``split_duration_s`` or
``split_size_mb`` it is ``<stem>_000.mcap``, ``<stem>_001.mcap``... beside ``path``, in the
way of rosbag2's ``--max-bag-duration`` / ``--max-bag-size``: every file is complete and
indexed on its own and carries the session's metadata and attachments (the configuration),
so any one of them opens alone; :func:`hil.core.recording.reader.read_session` reads the
series as one.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import IO, Any

from hil.core.recording.mcap_writer import McapWriter
from hil.core.recording.output import series_file

SPLIT_CHECK_EVERY = 256  # messages between two size checks
ZSTD_LEVEL = 9  # 12 MB/s on this data, about 12 % smaller than zstandard's default level 3
DEFAULT_CHUNK_BYTES = 1 << 20  # larger chunks compress better; the 1 s flush bounds them


@dataclass
class ChannelSpec:
    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes


@dataclass
class SeriesStats:
    messages_written: int = 0
    chunks_flushed: int = 0
    bytes_written: int = 0
    files: list[str] = field(default_factory=list)


class McapSeries:
    """Writes channels, messages, metadata and attachments; rolls files over when asked."""

    def __init__(
        self,
        path: str,
        *,
        chunk_size: int = DEFAULT_CHUNK_BYTES,
        chunk_span_s: float | None = None,
        zstd_level: int = ZSTD_LEVEL,
        split_duration_s: float | None = None,
        split_size_mb: float | None = None,
        profile: str = "",
        first_fd: int | None = None,
        staging: str | None = None,
    ) -> None:
        self.path = path
        # the first file, already open: a run's staging file, named ``staging`` until the run
        # starts; the series goes on to a second file only then (a run that never started
        # leaves none)
        self.first_fd = first_fd
        self.staging = staging
        self.chunk_size = chunk_size
        self.chunk_span_ns = round(chunk_span_s * 1e9) if chunk_span_s else None
        self.zstd_level = zstd_level
        self.split = split_duration_s is not None or split_size_mb is not None
        self.split_ns = round(split_duration_s * 1e9) if split_duration_s else None
        self.split_bytes = round(split_size_mb * 1e6) if split_size_mb else None
        self.profile = profile
        self.stats = SeriesStats()
        self._channels: dict[int, ChannelSpec] = {}
        self._metadata: list[tuple[str, dict[str, str]]] = []
        self._attachments: list[tuple[str, bytes, str, int]] = []
        self._file: IO[bytes] | None = None
        self._writer: McapWriter | None = None
        self._file_channels: dict[int, int] = {}
        self._file_first_ns: int | None = None
        self._since_check = 0
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        self._open(0)

    # -- files -----------------------------------------------------------------------------
    def _open(self, index: int) -> None:
        name = series_file(self.path, index) if self.split else self.path
        if index == 0 and self.first_fd is not None:
            self._file = open(self.first_fd, "wb")  # noqa: SIM115 - closed by _finish_file()
        else:
            self._file = open(name, "wb")  # noqa: SIM115 - closed by _finish_file()
        self._writer = McapWriter(self._file, chunk_size=self.chunk_size,
                                  chunk_span_ns=self.chunk_span_ns, zstd_level=self.zstd_level)
        self._writer.start(profile=self.profile, library="hil")
        self._file_channels = {}
        self._file_first_ns = None
        self.stats.files.append(name)
        for name_, data in self._metadata:
            self._writer.add_metadata(name_, data)
        for attachment in self._attachments:
            self._write_attachment(*attachment)
        for key in self._channels:  # every file lists every topic, with messages or not
            self._register(key)

    def _finish_file(self, extra_metadata: tuple[tuple[str, dict[str, str]], ...] = ()) -> None:
        assert self._writer is not None and self._file is not None
        for name, data in extra_metadata:
            self._writer.add_metadata(name, data)
        self._writer.finish()
        self.stats.bytes_written += self._file.tell()
        self._file.close()
        self._writer = None
        self._file = None

    def _maybe_roll(self, t_ns: int) -> None:
        if self._file_first_ns is None:
            self._file_first_ns = t_ns
            return
        due = self.split_ns is not None and t_ns - self._file_first_ns >= self.split_ns
        if not due and self.split_bytes is not None:
            self._since_check += 1
            if self._since_check >= SPLIT_CHECK_EVERY:
                self._since_check = 0
                assert self._file is not None
                due = self._file.tell() >= self.split_bytes
        if due and self.staging is not None and len(self.stats.files) == 1 and \
                os.path.exists(self.staging):
            due = False
        if due:
            self._finish_file()
            self._open(len(self.stats.files))
            self._file_first_ns = t_ns

    # -- records ---------------------------------------------------------------------------
    def add_channel(self, key: int, spec: ChannelSpec) -> None:
        self._channels[key] = spec
        self._register(key)

    def add_message(self, key: int, t_ns: int, payload: bytes) -> None:
        self.add_messages(((key, t_ns, payload),))

    def add_messages(self, messages: Sequence[tuple[int, int, bytes]]) -> None:
        """``(key, t_ns, payload)`` each, in order, in one call to the file's writer (one
        call each where the series splits: a file may end between two of them)."""
        if self.split:
            for message in messages:
                self._maybe_roll(message[1])
                self._add((message,))
            return
        self._add(messages)

    def _add(self, messages: Sequence[tuple[int, int, bytes]]) -> None:
        writer = self._writer
        assert writer is not None
        channels = self._file_channels
        writer.add_messages([(channels[key], t_ns, t_ns, payload)
                             for key, t_ns, payload in messages], self.stats.messages_written)
        self.stats.messages_written += len(messages)

    def _register(self, key: int) -> int:
        spec = self._channels[key]
        assert self._writer is not None
        schema_id = self._writer.register_schema(
            name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema_data)
        channel_id = self._writer.register_channel(
            topic=spec.topic, message_encoding=spec.message_encoding, schema_id=schema_id)
        self._file_channels[key] = channel_id
        return channel_id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Written now, and again at the head of every later file of the series."""
        self._metadata.append((name, data))
        assert self._writer is not None
        self._writer.add_metadata(name, data)

    def add_attachment(self, name: str, data: bytes, media_type: str, t_ns: int) -> None:
        self._attachments.append((name, data, media_type, t_ns))
        self._write_attachment(name, data, media_type, t_ns)

    def _write_attachment(self, name: str, data: bytes, media_type: str, t_ns: int) -> None:
        assert self._writer is not None
        self._writer.add_attachment(create_time=time.time_ns(), log_time=t_ns, name=name,
                                    data=data, media_type=media_type)

    def flush(self) -> None:
        """Close the chunk in progress and push it to the file (bounds what a crash loses)."""
        assert self._writer is not None
        self._writer.flush()
        self.stats.chunks_flushed += 1

    def close(self, final_metadata: dict[str, dict[str, str]] | None = None) -> SeriesStats:
        """Finish the current file; ``final_metadata`` goes into it (the last of the series)."""
        if self._writer is not None:
            self._finish_file(tuple((final_metadata or {}).items()))
        return self.stats


def json_schema_channel(topic: str, schema: dict[str, Any]) -> ChannelSpec:
    """A JSON channel described by its JSON Schema (Foxglove's native pairing)."""
    return ChannelSpec(topic, "json", str(schema.get("title", topic)), "jsonschema",
                       json.dumps(schema).encode())
