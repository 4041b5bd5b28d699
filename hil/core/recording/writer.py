"""The session's writer process: encoding, compression and file I/O off the loop's interpreter.

Forked for :class:`hil.core.recording.recorder.Recorder` by its process's fork server
(:mod:`hil.core.recording.writer_fork`), which then runs :func:`serve` with the recorder's
options and the record stream (:mod:`hil.core.recording.record_stream`) on its standard
input. It encodes each
message (JSON, or CDR for compact topics), writes the MCAP file or split series
(:class:`~hil.core.recording.mcap_series.McapSeries`), closes a chunk at least every
``flush_interval_s`` of wall time and every ``chunk_span_s`` of session time, and finishes
the file with its summary and index when the stream says ``close`` *or* simply ends: a
SIGKILLed loop process still leaves a finished, indexed file, missing only what it had not yet
handed over. A run's session is written to its staging file
(``first_fd``, ``staging``: :mod:`hil.core.recording.output`); if that file still bears its
staging name when the writing ends, the run never started, and the writer removes it. Its last
act is one JSON line of statistics on standard output.

It runs in its own session (process group) and ignores SIGINT and SIGTERM, so a Ctrl-C or a
signal to the run's process group lets the loop process drain into it before the stream ends.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import select
import signal
import sys
import time
from array import array
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from hil.core.recording.cdr import CdrEncoder, fields_of, ros2msg_text
from hil.core.recording.mcap_series import (
    DEFAULT_CHUNK_BYTES,
    ZSTD_LEVEL,
    ChannelSpec,
    McapSeries,
    json_schema_channel,
)
from hil.core.recording.output import remove_if_same
from hil.core.recording.record_stream import FrameDecoder

if TYPE_CHECKING:
    from hil.core.recording.live import LiveSink

EVENTS_KEY = 0  # the recorder registers /events first
READ_BYTES = 1 << 20
WRITER_NICENESS = 10  # where SCHED_IDLE is refused


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):  # numpy arrays and scalars, without importing numpy here
        return value.tolist()
    raise TypeError(f"cannot record a {type(value).__name__} as JSON")


def encode_json(message: Any) -> bytes:
    """The one JSON encoding of recorded messages (compact, numpy-aware)."""
    return json.dumps(message, separators=(",", ":"), default=_json_default).encode()


@dataclasses.dataclass(frozen=True)
class TopicEncoding:
    """How a topic's messages become bytes: as dicts (``encode``), or as packed rows (the
    values of the schema's properties in order, None where a message leaves a field out):
    CDR encodes a row as it is (``cdr_row``), JSON the dict the row stands for."""

    names: tuple[str, ...]
    encode: Callable[[Any], bytes]
    cdr_row: Callable[[tuple[Any, ...]], bytes] | None = None

    def row_message(self, row: tuple[Any, ...]) -> dict[str, Any]:
        """The dict a row stands for."""
        return {name: value for name, value in zip(self.names, row, strict=True)
                if value is not None}

    def encode_row(self, row: tuple[Any, ...]) -> bytes:
        if len(row) != len(self.names):
            raise ValueError(f"a row of {len(row)} value(s) for a topic of "
                             f"{len(self.names)} field(s) ({', '.join(self.names)})")
        return self.cdr_row(row) if self.cdr_row is not None else \
            self.encode(self.row_message(row))


def channel_for(name: str, schema: dict[str, Any], encoding: str
                ) -> tuple[ChannelSpec, TopicEncoding]:
    """The MCAP channel of a topic and how its messages are encoded."""
    names = tuple(schema.get("properties") or ())
    if encoding == "cdr":
        fields = fields_of(schema)
        title = str(schema.get("title", name.strip("/").replace("/", "_")))
        spec = ChannelSpec(name, "cdr", title.replace(".", "/msg/", 1) if "." in title
                           else f"hil/msg/{title}", "ros2msg", ros2msg_text(fields).encode())
        encoder = CdrEncoder(fields)
        return spec, TopicEncoding(names, encoder.encode, encoder.encode_row)
    return json_schema_channel(name, schema), TopicEncoding(names, encode_json)


class SessionWriter:
    """Applies records of the stream to a :class:`McapSeries` (and a live view, if any)."""

    def __init__(self, series: McapSeries, live: LiveSink | None = None) -> None:
        self.series = series
        self.live = live
        self.encodings: dict[int, TopicEncoding] = {}
        self.dropped: dict[str, int] = {}
        self.closed = False
        self.last_t_ns = 0
        self.applied = 0  # of the records given to apply_all
        #: the columns of each column topic's message being built (recorder.ColumnTopic)
        self.columns: dict[int, list[array[float]]] = {}

    def add_row(self, key: int, row: tuple[float, ...]) -> None:
        """One row of ``key``'s next message: a value appended to each of its columns."""
        columns = self.columns.get(key)
        if columns is None:
            columns = self.columns[key] = [array("d") for _ in row]
        for column, value in zip(columns, row, strict=True):
            column.append(value)

    def column_message(self, key: int, fields: dict[str, Any] | None,
                       names: tuple[str, ...]) -> dict[str, Any] | None:
        """``fields`` with the rows added to ``key`` since its last message as the columns
        ``names``; None (the rows let go) when ``fields`` is None: a row was lost."""
        columns = self.columns.pop(key, None) or [array("d") for _ in names]
        if fields is None:
            return None
        return {**fields, **dict(zip(names, columns, strict=True))}

    def apply(self, record: tuple[Any, ...]) -> None:
        kind = record[0]
        if isinstance(kind, int):
            _, t_ns, message = record
            encoding = self.encodings[kind]
            if type(message) is tuple:  # a packed row: the schema's properties in order
                data = encoding.encode_row(message)
                if self.live is not None:
                    message = encoding.row_message(message)
            else:
                data = encoding.encode(message)
            self.series.add_message(kind, t_ns, data)
            self.last_t_ns = t_ns
            if self.live is not None:
                self.live.log(kind, t_ns, message)
        elif type(kind) is tuple:  # a topic group's rows (recorder.TopicRows): one a topic
            _, t_ns, rows = record
            for key, row in zip(kind, rows, strict=True):
                self.apply((key, t_ns, row))
        elif kind == "row":
            self.add_row(record[1], record[2])
        elif kind == "message":
            _, key, t_ns, fields, names = record
            message = self.column_message(key, fields, names)
            if message is not None:
                self.apply((key, t_ns, message))
        elif kind == "topic":
            _, key, name, schema, encoding_name = record
            spec, self.encodings[key] = channel_for(name, schema, encoding_name)
            self.series.add_channel(key, spec)
            if self.live is not None:
                self.live.add_topic(key, name, schema)
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

    def apply_all(self, records: Sequence[tuple[Any, ...]]) -> None:
        """:meth:`apply` each of ``records`` in order, in fewer calls: a run of messages is
        encoded in one loop and handed to the series at once (the same bytes). A message
        that cannot be encoded fails it as it fails :meth:`apply`, the messages before it
        written; :attr:`applied` then says how many records were (none of a run the series
        failed to take)."""
        self.applied = 0
        if self.live is not None:  # the live view takes each message as a dict
            for record in records:
                self.apply(record)
                self.applied += 1
            return
        encodings = self.encodings
        run: list[tuple[int, int, bytes]] = []
        at = 0
        try:
            for at, record in enumerate(records):
                kind = record[0]
                if type(kind) is int:
                    message = record[2]
                    encoding = encodings[kind]
                    run.append((kind, record[1], encoding.encode_row(message)
                                if type(message) is tuple else encoding.encode(message)))
                elif type(kind) is tuple:  # a topic group's rows (recorder.TopicRows)
                    t_ns = record[1]
                    for key, row in zip(kind, record[2], strict=True):
                        run.append((key, t_ns, encodings[key].encode_row(row)))
                elif kind == "row":  # a row of a column topic's message: no message yet
                    self.add_row(record[1], record[2])
                else:
                    done, run = run, []
                    self._add_messages(done)
                    self.applied = at
                    self.apply(record)
                    self.applied = at + 1
        except Exception:
            if run:  # a message failed to encode: those before it are written, as by apply
                self._add_messages(run)
                self.applied = at
            raise
        self._add_messages(run)
        self.applied = len(records)

    def _add_messages(self, messages: list[tuple[int, int, bytes]]) -> None:
        if messages:
            self.series.add_messages(messages)
            self.last_t_ns = messages[-1][1]

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
        if EVENTS_KEY in self.encodings:
            event = {"level": "warning", "source": "recorder", "kind": kind, "message": message,
                     "data": data}
            self.series.add_message(EVENTS_KEY, t_ns, encode_json(event))
            if self.live is not None:
                self.live.log(EVENTS_KEY, t_ns, event)

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


def start_live(options: dict[str, Any]) -> LiveSink | None:
    """The session's live view when ``options["live"]`` asks for one; its URL on stderr.
    With ``options["tune_fd"]`` (the reverse channel to the loop process, see
    :mod:`hil.core.recording.tune_wire`) it serves the run's parameters too, read-only beyond
    loopback unless ``options["live_remote_tuning"]``.

    A live view that cannot start is reported on stderr and left out: the file comes first.
    """
    if not options.get("live"):
        return None
    # imported here: a writer without a live view (most) spares their start-up
    import socket

    from hil.core.recording.live import LiveSink, announce, parse_address
    from hil.core.recording.tune_wire import RemotePort

    tune_fd = options.get("tune_fd")
    parameters = RemotePort(socket.socket(fileno=tune_fd)) if tune_fd is not None else None
    try:
        host, port = parse_address(options["live"])
        live = LiveSink(host, port, rates=options.get("live_rates") or {},
                        parameters=parameters,
                        remote_tuning=bool(options.get("live_remote_tuning")))
    except Exception as exc:  # any failure of the server must not cost the recording
        print(f"hil: warning: live view off: {exc}", file=sys.stderr, flush=True)
        return None
    announce(live.url, live.exposure)
    return live


def describe_failure(exc: BaseException) -> str:
    """A writer failure in one line: an OS error by its reason and file (``No space left on
    device``, ``File too large``), anything else by its type and message."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.strerror}" + (f" ({exc.filename})" if exc.filename else "")
    return f"{type(exc).__name__}: {exc}"


def open_series(options: dict[str, Any]) -> McapSeries:
    """The session's file (or split series) as ``options`` describe it (the recorder's)."""
    return McapSeries(
        options["path"], chunk_size=int(options.get("chunk_size", DEFAULT_CHUNK_BYTES)),
        chunk_span_s=options.get("chunk_span_s"),
        zstd_level=int(options.get("zstd_level", ZSTD_LEVEL)),
        split_duration_s=options.get("split_duration_s"),
        split_size_mb=options.get("split_size_mb"), profile=options.get("profile", ""),
        first_fd=options.get("first_fd"), staging=options.get("staging"),
    )


def finish(writer: SessionWriter, error: str, cut: int = 0) -> dict[str, Any]:
    """Finish the file (summary, index, the recorder's final metadata) and return the
    statistics; a failure to finish it is the report's ``error`` unless one came first."""
    metadata = writer.final_metadata(cut, error)
    live = writer.live
    live_stats = dataclasses.asdict(live.stats()) if live is not None else {}
    if live_stats:
        metadata["live"] = {key: json.dumps(value) for key, value in live_stats.items()}
    try:
        stats = writer.series.close(metadata)
    except Exception as exc:  # the disk is full, say: what is in the file stays readable
        error = error or describe_failure(exc)
        stats = writer.series.stats
    return {"messages_written": stats.messages_written, "chunks_flushed": stats.chunks_flushed,
            "bytes_written": stats.bytes_written, "files": stats.files,
            "dropped": writer.dropped, "closed": writer.closed, "error": error,
            "live": live_stats}


def run(options: dict[str, Any], fd: int = 0, ready: Callable[[], None] = lambda: None
        ) -> dict[str, Any]:
    """Write the session read from ``fd`` until ``close`` or end of file; return statistics.
    ``ready`` is called once the file is open, before the first read. A failure (the file
    cannot be opened or written, a message cannot be encoded) ends the writing: what was
    written stays in the file and the statistics name the failure (``error``)."""
    first_fd = options.get("first_fd")
    staging = os.fstat(first_fd) if first_fd is not None else None
    try:
        series = open_series(options)
    except Exception as exc:
        return {"messages_written": 0, "error": describe_failure(exc), "closed": False}
    live = start_live(options)  # serving before the loop starts
    ready()
    writer = SessionWriter(series, live)
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
                    writer.apply_all(records)
            if time.monotonic() >= next_flush:
                series.flush()
                next_flush = time.monotonic() + flush_interval
    except Exception as exc:  # reported in the file and to the loop process
        error = describe_failure(exc)
    cut = decoder.pending_bytes
    if cut and not error:
        writer.event(writer.last_t_ns, "recorder.stream_cut",
                     f"the loop process ended in the middle of a batch ({cut} bytes lost)",
                     bytes=cut)
    result = finish(writer, error, cut)
    if staging is not None:  # the run never started (its loop process may be gone): no file
        remove_if_same(options["staging"], staging)
    if live is not None:  # after the file: a stalled client may hold the server's stop
        live.close()
    return result


def yield_cpu() -> None:
    """Run only when the CPU has nothing else to do (SCHED_IDLE): an emulator woken up on
    this CPU then always preempts the writer at once; a backlog absorbs a late writer. Where
    SCHED_IDLE is refused, nice 10."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        with contextlib.suppress(OSError):
            os.nice(WRITER_NICENESS)


def serve(options: dict[str, Any]) -> int:
    """The writer process's whole life, its record stream on standard input, "ready" then
    its statistics on standard output; the exit status (1: the writing failed)."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    if options.get("yield_cpu"):  # real time: the loop, the drive and its emulator come first
        yield_cpu()
        # unpickling a numpy message imports numpy (0.1-0.2 s of CPU): in real time, do it
        # before 'ready' rather than beside the first ticks
        import numpy  # noqa: F401

    def ready() -> None:
        with contextlib.suppress(OSError):  # the loop process may be gone already
            print("ready", flush=True)

    try:
        result = run(options, ready=ready)
    except BaseException as exc:  # never a traceback: the loop process reports the failure
        result = {"messages_written": 0, "error": describe_failure(exc), "closed": False}
    with contextlib.suppress(OSError):  # nobody listens any more: the loop process is gone
        print(json.dumps(result), flush=True)
    return 1 if result["error"] else 0
