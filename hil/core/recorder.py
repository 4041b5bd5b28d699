"""MCAP recorder: the loop thread only enqueues, a writer thread serialises and writes.

* Every topic is JSON with a JSON Schema (Foxglove opens it without a plug-in).
* A bounded queue: when it is full the message is dropped and counted; the counts are written
  to ``/events`` as soon as the writer catches up, and in the summary at close. In lockstep
  (``wait_when_full``) the producer waits for the writer instead: virtual time costs nothing,
  and a lockstep run that outpaces the disk must not lose samples.
* Chunks of ``chunk_size`` bytes (128 KiB default) and a flush at least every
  ``flush_interval_s``: a SIGKILLed process loses about one second of messages at most.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer

from hil.core.errors import HilError

EVENTS_TOPIC = "/events"

EVENT_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.Event",
    "description": "Something that happened: a fault, a fallback, a state change, dropped data.",
    "properties": {
        "level": {"type": "string", "enum": ["debug", "info", "warning", "error"]},
        "source": {"type": "string"},
        "kind": {"type": "string"},
        "message": {"type": "string"},
        "data": {"type": "object"},
    },
    "required": ["level", "kind", "message"],
}


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot record a {type(value).__name__} as JSON")


def encode_json(message: Any) -> bytes:
    """The one JSON encoding of recorded messages (compact, numpy-aware)."""
    return json.dumps(message, separators=(",", ":"), default=_json_default).encode()


class RecorderError(HilError):
    """The writer thread failed; what it wrote before is in the file, the rest was dropped."""


@dataclass
class RecorderStats:
    messages_written: int
    messages_dropped: dict[str, int]
    chunks_flushed: int
    bytes_written: int


class Topic:
    """A registered channel; :meth:`log` is the loop thread's whole cost of recording."""

    __slots__ = ("_recorder", "channel_key", "dropped", "name")

    def __init__(self, recorder: Recorder, name: str, channel_key: int) -> None:
        self._recorder = recorder
        self.name = name
        self.channel_key = channel_key
        self.dropped = 0

    def log(self, t_ns: int, message: Any) -> bool:
        """Hand ``message`` (JSON-able; numpy allowed) stamped ``t_ns`` to the writer.

        Returns False when the queue was full and the message was dropped (and counted).
        The message object must not be mutated afterwards.
        """
        rec = self._recorder
        if len(rec._queue) >= rec.queue_size and rec.wait_when_full and not rec._closing:
            rec._wait_for_room()
        if len(rec._queue) >= rec.queue_size or rec._closing:
            self.dropped += 1
            return False
        rec._queue.append((self.channel_key, t_ns, message))
        return True


class Recorder:
    """Writes one MCAP file from any number of producer threads."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        queue_size: int = 200_000,
        chunk_size: int = 128 * 1024,
        flush_interval_s: float = 1.0,
        profile: str = "",
        wait_when_full: bool = False,
    ) -> None:
        self.path = os.fspath(path)
        self.queue_size = queue_size
        self.wait_when_full = wait_when_full
        self.flush_interval_s = flush_interval_s
        self._queue: deque[tuple[int, int, Any]] = deque()
        self._closing = False
        self._lock = threading.Lock()
        self._pending_setup: list[tuple[str, tuple[Any, ...]]] = []
        self._topics: dict[str, Topic] = {}
        self._channel_ids: dict[int, int] = {}
        self._reported_drops: dict[str, int] = {}
        self._written = 0
        self._chunks = 0
        self._failure: Exception | None = None
        self._stats: RecorderStats | None = None
        self._last_t_ns = 0
        directory = os.path.dirname(os.path.abspath(self.path))
        os.makedirs(directory, exist_ok=True)
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed by close()
        self._writer = Writer(
            self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD
        )
        self._writer.start(profile=profile, library="hil")
        self.events = self.topic(EVENTS_TOPIC, EVENT_SCHEMA)
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        self._thread.start()

    # -- producer side -------------------------------------------------------------------
    def topic(self, name: str, schema: dict[str, Any]) -> Topic:
        """Register (or get) a JSON topic with its JSON Schema."""
        with self._lock:
            existing = self._topics.get(name)
            if existing is not None:
                return existing
            topic = Topic(self, name, len(self._topics))
            self._topics[name] = topic
            self._pending_setup.append(("topic", (topic.channel_key, name, schema)))
            return topic

    def event(
        self, t_ns: int, kind: str, message: str, level: str = "info", source: str = "", **data: Any
    ) -> None:
        """Record an event on ``/events``."""
        self.events.log(
            t_ns, {"level": level, "source": source, "kind": kind, "message": message, "data": data}
        )

    def metadata(self, name: str, data: dict[str, str]) -> None:
        """Add a metadata record (string to string map)."""
        with self._lock:
            self._pending_setup.append(("metadata", (name, dict(data))))

    def attachment(self, name: str, data: bytes, media_type: str, t_ns: int = 0) -> None:
        """Attach a file (e.g. the configuration)."""
        with self._lock:
            self._pending_setup.append(("attachment", (name, bytes(data), media_type, t_ns)))

    def _wait_for_room(self) -> None:
        """Block the producer until the writer has drained half the queue (lockstep only)."""
        while len(self._queue) > self.queue_size // 2 and self._thread.is_alive():
            time.sleep(0.002)

    def dropped(self) -> dict[str, int]:
        return {name: t.dropped for name, t in self._topics.items() if t.dropped}

    # -- writer side ---------------------------------------------------------------------
    def _apply_setup(self) -> None:
        with self._lock:
            pending, self._pending_setup = self._pending_setup, []
        for kind, args in pending:
            if kind == "topic":
                key, name, schema = args
                schema_id = self._writer.register_schema(
                    name=schema.get("title", name), encoding="jsonschema",
                    data=json.dumps(schema).encode(),
                )
                self._channel_ids[key] = self._writer.register_channel(
                    topic=name, message_encoding="json", schema_id=schema_id
                )
            elif kind == "metadata":
                self._writer.add_metadata(*args)
            else:
                name, data, media_type, t_ns = args
                self._writer.add_attachment(
                    create_time=time.time_ns(), log_time=t_ns, name=name, data=data,
                    media_type=media_type,
                )

    def _drain(self) -> None:
        queue, channel_ids, writer = self._queue, self._channel_ids, self._writer
        while queue:
            key, t_ns, message = queue.popleft()
            if key not in channel_ids:  # registered after this cycle's setup: register it now
                self._apply_setup()
            writer.add_message(
                channel_id=channel_ids[key], log_time=t_ns, publish_time=t_ns,
                data=encode_json(message), sequence=self._written,
            )
            self._written += 1
            self._last_t_ns = t_ns
            os.sched_yield()  # let a waiting loop thread take the GIL between two messages

    def _report_drops(self) -> None:
        for name, count in self.dropped().items():
            before = self._reported_drops.get(name, 0)
            if count > before:
                self._reported_drops[name] = count
                self._queue.append((self.events.channel_key, self._last_t_ns, {
                    "level": "warning", "source": "recorder", "kind": "recorder.dropped",
                    "message": f"{count - before} message(s) on {name} dropped (queue full)",
                    "data": {"topic": name, "dropped": count - before, "total": count},
                }))

    def _flush(self) -> None:
        self._writer.flush()
        self._chunks += 1

    def _run(self) -> None:
        try:
            self._write_until_closed()
        except Exception as exc:  # surfaced by close(); from now on producers drop and count
            self._failure = exc
            self._closing = True

    def _write_until_closed(self) -> None:
        last_flush = time.monotonic()
        while True:
            closing = self._closing
            self._apply_setup()
            self._drain()
            self._report_drops()
            self._drain()
            now = time.monotonic()
            if now - last_flush >= self.flush_interval_s:
                self._flush()
                last_flush = now
            if closing and not self._queue:
                return
            time.sleep(0.005)

    # -- lifecycle -------------------------------------------------------------------------
    def close(self) -> RecorderStats:
        """Write everything queued, the summary and the index; return what happened."""
        if self._stats is not None:
            return self._stats
        self._closing = True
        self._thread.join()
        try:
            if self._failure is None:
                self._apply_setup()
                self._drain()
            drops = self.dropped()
            if drops:
                self._writer.add_metadata("recorder", {"dropped": json.dumps(drops)})
            self._writer.finish()
        finally:
            self._file.close()
        self._stats = RecorderStats(
            messages_written=self._written, messages_dropped=drops,
            chunks_flushed=self._chunks, bytes_written=os.path.getsize(self.path),
        )
        if self._failure is not None:
            raise RecorderError(
                f"{self.path}: recording stopped after {self._written} message(s): the writer "
                f"failed with {type(self._failure).__name__}: {self._failure}; "
                f"{sum(drops.values())} later message(s) were dropped"
            ) from self._failure
        return self._stats

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
