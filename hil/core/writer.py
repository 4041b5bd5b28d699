"""The session's writer process: encoding, compression and file I/O off the loop's interpreter.

Started by :class:`hil.core.recorder.Recorder` as ``python -m hil.core.writer OPTIONS_JSON``
with the record stream (:mod:`hil.core.record_stream`) on its standard input. It encodes each
message (JSON, or CDR for compact topics), writes the MCAP file or split series
(:class:`~hil.core.mcap_series.McapSeries`), closes a chunk at least every
``flush_interval_s``, and finishes the file with its summary and index when the stream says
``close`` *or* simply ends: a SIGKILLed loop process still leaves a finished, indexed file,
missing only what it had not yet handed over. Its last act is one JSON line of statistics on
standard output.

It runs in its own session (process group) and ignores SIGINT and SIGTERM, so a Ctrl-C or a
signal to the run's process group lets the loop process drain into it before the stream ends.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import sys
import time
from collections.abc import Callable
from typing import Any

from hil.core.cdr import CdrEncoder, fields_of, ros2msg_text
from hil.core.mcap_series import (
    DEFAULT_CHUNK_BYTES,
    ChannelSpec,
    McapSeries,
    json_schema_channel,
    use_zstd_level,
)
from hil.core.record_stream import FrameDecoder

EVENTS_KEY = 0  # the recorder registers /events first
READ_BYTES = 1 << 20
WRITER_NICENESS = 10  # a backlog absorbs a late writer; a late emulator or loop is a fault


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):  # numpy arrays and scalars, without importing numpy here
        return value.tolist()
    raise TypeError(f"cannot record a {type(value).__name__} as JSON")


def encode_json(message: Any) -> bytes:
    """The one JSON encoding of recorded messages (compact, numpy-aware)."""
    return json.dumps(message, separators=(",", ":"), default=_json_default).encode()


def channel_for(name: str, schema: dict[str, Any], encoding: str
                ) -> tuple[ChannelSpec, Callable[[Any], bytes]]:
    """The MCAP channel of a topic and the function that encodes its messages."""
    if encoding == "cdr":
        fields = fields_of(schema)
        title = str(schema.get("title", name.strip("/").replace("/", "_")))
        spec = ChannelSpec(name, "cdr", title.replace(".", "/msg/", 1) if "." in title
                           else f"hil/msg/{title}", "ros2msg", ros2msg_text(fields).encode())
        return spec, CdrEncoder(fields).encode
    return json_schema_channel(name, schema), encode_json


class SessionWriter:
    """Applies records of the stream to a :class:`McapSeries`."""

    def __init__(self, series: McapSeries) -> None:
        self.series = series
        self.encoders: dict[int, Callable[[Any], bytes]] = {}
        self.dropped: dict[str, int] = {}
        self.closed = False
        self.last_t_ns = 0

    def apply(self, record: tuple[Any, ...]) -> None:
        kind = record[0]
        if isinstance(kind, int):
            _, t_ns, message = record
            self.series.add_message(kind, t_ns, self.encoders[kind](message))
            self.last_t_ns = t_ns
        elif kind == "topic":
            _, key, name, schema, encoding = record
            spec, self.encoders[key] = channel_for(name, schema, encoding)
            self.series.add_channel(key, spec)
        elif kind == "metadata":
            self.series.add_metadata(record[1], record[2])
        elif kind == "attachment":
            self.series.add_attachment(*record[1:])
        elif kind == "drops":
            self._report_drops(record[1], record[2])
        elif kind == "close":
            self.closed = True
        else:
            raise ValueError(f"unknown record {kind!r} in the record stream")

    def _report_drops(self, t_ns: int, totals: dict[str, int]) -> None:
        for topic, total in totals.items():
            new = total - self.dropped.get(topic, 0)
            if new <= 0:
                continue
            self.dropped[topic] = total
            self.event(max(t_ns, self.last_t_ns), "recorder.dropped",
                       f"{new} message(s) on {topic} dropped (the writer fell behind)",
                       topic=topic, dropped=new, total=total)

    def event(self, t_ns: int, kind: str, message: str, **data: Any) -> None:
        if EVENTS_KEY in self.encoders:
            self.series.add_message(EVENTS_KEY, t_ns, encode_json({
                "level": "warning", "source": "recorder", "kind": kind, "message": message,
                "data": data}))

    def final_metadata(self, cut_bytes: int, error: str) -> dict[str, dict[str, str]]:
        recorder: dict[str, str] = {}
        if self.dropped:
            recorder["dropped"] = json.dumps(self.dropped)
        if not self.closed:
            recorder["ended"] = "the loop process ended without closing the session"
        if cut_bytes:
            recorder["stream_cut_bytes"] = str(cut_bytes)
        if error:
            recorder["error"] = error
        return {"recorder": recorder} if recorder else {}


def run(options: dict[str, Any], fd: int = 0, ready: Callable[[], None] = lambda: None
        ) -> dict[str, Any]:
    """Write the session read from ``fd`` until ``close`` or end of file; return statistics.
    ``ready`` is called once the file is open, before the first read."""
    series = McapSeries(
        options["path"], chunk_size=int(options.get("chunk_size", DEFAULT_CHUNK_BYTES)),
        split_duration_s=options.get("split_duration_s"),
        split_size_mb=options.get("split_size_mb"), profile=options.get("profile", ""),
    )
    ready()
    writer = SessionWriter(series)
    decoder = FrameDecoder()
    flush_interval = float(options.get("flush_interval_s", 1.0))
    next_flush = time.monotonic() + flush_interval
    error = ""
    try:
        while not writer.closed:
            timeout = max(0.0, next_flush - time.monotonic())
            if select.select([fd], [], [], timeout)[0]:
                data = os.read(fd, READ_BYTES)
                if not data:
                    break
                for records in decoder.feed(data):
                    for record in records:
                        writer.apply(record)
            if time.monotonic() >= next_flush:
                series.flush()
                next_flush = time.monotonic() + flush_interval
    except Exception as exc:  # reported in the file and to the loop process
        error = f"{type(exc).__name__}: {exc}"
    cut = decoder.pending_bytes
    if cut and not error:
        writer.event(writer.last_t_ns, "recorder.stream_cut",
                     f"the loop process ended in the middle of a batch ({cut} bytes lost)",
                     bytes=cut)
    stats = series.close(writer.final_metadata(cut, error))
    return {"messages_written": stats.messages_written, "chunks_flushed": stats.chunks_flushed,
            "bytes_written": stats.bytes_written, "files": stats.files,
            "dropped": writer.dropped, "closed": writer.closed, "error": error}


def main() -> int:
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    with contextlib.suppress(OSError):  # the loop, the drive and its emulator come first
        os.nice(WRITER_NICENESS)
    use_zstd_level()
    import numpy  # noqa: F401 - unpickling numpy messages needs it: import it before 'ready'

    def ready() -> None:
        print("ready", flush=True)

    result = run(json.loads(sys.argv[1]), ready=ready)
    with contextlib.suppress(OSError):  # nobody listens any more: the loop process is gone
        print(json.dumps(result), flush=True)
    return 1 if result["error"] else 0


if __name__ == "__main__":
    sys.exit(main())
