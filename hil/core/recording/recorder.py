"""MCAP recorder, loop side: producers only queue; a writer *process* encodes and writes.

* :meth:`Topic.log` appends ``(channel, t_ns, message)`` to a queue: the whole cost on the
  loop thread (a :class:`TopicRows` appends ``(channels, t_ns, rows)``: several topics' rows
  of one time in one record, for the writer to split). :meth:`Recorder.flush` (the loop
  calls it once per tick, at most every ``flush_every_s`` of wall time) pickles the queue as
  one frame and writes it, without blocking, to a pipe read by the writer process
  (:mod:`hil.core.recording.writer`). JSON or CDR encoding, zstd compression and file I/O
  happen there, off this interpreter's GIL.
* Back-pressure: what the pipe does not take waits in a backlog of at most
  ``max_backlog_bytes``; beyond it messages are dropped at :meth:`Topic.log` and counted per
  topic, and the counts reach ``/events`` (``recorder.dropped``) and the file's ``recorder``
  metadata. In lockstep (``wait_when_full``) the producer waits for the writer instead:
  virtual time costs nothing, and a lockstep run must not lose samples.
* Crash safety: the writer closes a chunk at least every ``flush_interval_s`` of wall time
  and every ``chunk_span_s`` of session time (by default the same: a damaged chunk costs a
  lockstep session no more of its time than a real-time one), and finishes the file when the
  pipe ends, so a SIGKILL of the loop process loses only what was not yet
  handed over (at most ``flush_every_s`` plus one unflushed chunk), and the file is indexed.
* Encodings: ``json`` (JSON Schema) by default; ``cdr`` (ros2msg schema, see
  :mod:`hil.core.recording.cdr`) for flat high-rate topics.
* In process (``RecordingOptions.in_process``, lockstep only): no writer process; each flush
  hands the records to an :class:`~hil.core.recording.in_process.InProcessWriter` on the loop
  thread instead, which writes them with the writer process's code (a sweep's trials on Ray:
  every core already runs a trial), a ``batch_size`` at a time (or every
  ``flush_interval_s``): a SIGKILL loses the queue and the chunk in progress either way. A
  failure to write is the same RecordingError.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import select
import signal
import socket
import subprocess
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from hil.core.realtime import keep_process_off_cpu
from hil.core.recording.cdr import CdrError, fields_of
from hil.core.recording.output import OutputClaim
from hil.core.recording.record_stream import FrameDecoder, encode_frame
from hil.core.recording.recording_options import ENCODINGS, RecordingOptions
from hil.errors import HilError, RecordingError

if TYPE_CHECKING:  # imported where used: most runs write in a writer process, untuned
    from hil.core.recording.in_process import InProcessWriter
    from hil.core.recording.tune_wire import PortServer
    from hil.core.recording.writer_fork import ForkedWriter

EVENTS_TOPIC = "/events"
PIPE_BYTES = 1 << 20          # asked of the kernel for the pipe (Linux caps it at pipe-max-size)
WRITER_START_TIMEOUT_S = 30.0
WRITER_CLOSE_TIMEOUT_S = 120.0
WRITER_CHECK_EVERY_S = 0.1    # how often the loop looks whether the writer process still runs

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


@dataclass
class RecorderStats:
    messages_written: int
    messages_dropped: dict[str, int]
    chunks_flushed: int
    bytes_written: int
    files: list[str] = field(default_factory=list)


class Topic:
    """A registered channel; :meth:`log` is the loop thread's whole cost of recording."""

    __slots__ = ("_recorder", "channel_key", "dropped", "encoding", "name")

    def __init__(self, recorder: Recorder, name: str, channel_key: int, encoding: str) -> None:
        self._recorder = recorder
        self.name = name
        self.channel_key = channel_key
        self.encoding = encoding
        self.dropped = 0

    def log(self, t_ns: int, message: Any) -> bool:
        """Queue ``message`` (JSON-able; numpy allowed) stamped ``t_ns`` for the writer.

        ``message`` is a dict, or a packed row: a tuple of the values of the schema's
        properties in their order, None for one the message leaves out (cheaper to build and
        to hand over; the writer turns it into the same dict, so the file is the same).

        Returns False when it was dropped (backlog full, or the recorder closed) and counted.
        The message object must not be mutated afterwards.
        """
        rec = self._recorder
        if rec._refusing:
            self.dropped += 1
            return False
        rec._queue.append((self.channel_key, t_ns, message))
        if len(rec._queue) >= rec.batch_size:
            rec.flush()
        return True


class TopicRows:
    """Several topics logged together at one time, one packed row each (the axes of a bus,
    every tick): one hand-over for them all, which the writer makes into one message a topic,
    in order, the messages :meth:`Topic.log` would have made of each row."""

    __slots__ = ("_recorder", "keys", "topics")

    def __init__(self, recorder: Recorder, topics: tuple[Topic, ...]) -> None:
        self._recorder = recorder
        self.topics = topics
        self.keys = tuple(topic.channel_key for topic in topics)

    def log(self, t_ns: int, rows: tuple[tuple[Any, ...], ...]) -> bool:
        """Queue ``rows`` (one packed row per topic, in the order of :attr:`topics`) stamped
        ``t_ns``. Returns False when they were dropped (each topic counts its message).
        Inline as :meth:`Topic.log` is, not through a shared call: both run every tick."""
        rec = self._recorder
        if rec._refusing:
            for topic in self.topics:
                topic.dropped += 1
            return False
        rec._queue.append((self.keys, t_ns, rows))
        if len(rec._queue) >= rec.batch_size:
            rec.flush()
        return True


class ColumnTopic:
    """A topic whose messages carry columns of numbers built up in the writer a row at a
    time (the loop's timing windows: lateness and phase times). :meth:`add` hands over one
    row, a few numbers, each tick; :meth:`log` then has the writer make the message of the
    rows since the last one, its columns, with the other fields given. No tick hands over a
    window's worth: at 2 kHz, a second's columns (80 KB) pickled at once made the tick after
    every whole second late.

    A row refused (backlog full, recorder closed) loses its whole message, counted as one
    dropped message of the topic, as :meth:`Topic.log` counts one."""

    __slots__ = ("_lost", "_recorder", "topic")

    def __init__(self, recorder: Recorder, topic: Topic) -> None:
        self._recorder = recorder
        self.topic = topic
        self._lost = False  # a row of the message being built was refused

    def add(self, row: tuple[float, ...]) -> None:
        """One row: a value for each column, in the order :meth:`log` will name them."""
        rec = self._recorder
        if rec._refusing:
            self._lost = True
            return
        rec._queue.append(("row", self.topic.channel_key, row))
        if len(rec._queue) >= rec.batch_size:
            rec.flush()

    def log(self, t_ns: int, fields: dict[str, Any], columns: tuple[str, ...]) -> bool:
        """The message stamped ``t_ns``: ``fields``, and each of ``columns`` as the values of
        the rows added since the last message (in that position of each row). Returns False
        when it was dropped (and counted)."""
        rec = self._recorder
        if rec._refusing:
            self.topic.dropped += 1
            self._lost = True
            return False
        key = self.topic.channel_key
        if self._lost:  # the writer lets the rows it holds go, not made into a message
            rec._queue.append(("message", key, t_ns, None, columns))
            self.topic.dropped += 1
            self._lost = False
            return False
        rec._queue.append(("message", key, t_ns, fields, columns))
        if len(rec._queue) >= rec.batch_size:
            rec.flush()
        return True


class Recorder:
    """Writes one MCAP session (file or split series) through a writer process (or, with
    ``options.in_process``, in this process); with a ``claim``
    (:func:`hil.core.recording.output.claim_output`), its first file goes to the claim's
    staging file until the claim is started."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        chunk_size: int = 1 << 20,
        flush_interval_s: float = 1.0,
        chunk_span_s: float | None = 1.0,
        flush_every_s: float = 0.005,
        batch_size: int = 512,
        max_backlog_bytes: int = 64 << 20,
        profile: str = "",
        wait_when_full: bool = False,
        options: RecordingOptions | None = None,
        tunable: bool = False,
        claim: OutputClaim | None = None,
    ) -> None:
        self.path = os.fspath(path)
        self.options = options or RecordingOptions()
        self.wait_when_full = wait_when_full
        if self.options.in_process:
            self._check_in_process()
        # in process, a hand-over is the writing itself and a crash loses the queue and the
        # chunk in progress alike: the queue goes over when it holds ``batch_size`` records,
        # or at the writer's own wall-time flush
        self.flush_every_s = flush_interval_s if self.options.in_process else flush_every_s
        self.batch_size = batch_size
        self.max_backlog_bytes = max_backlog_bytes
        self._queue: deque[tuple[Any, ...]] = deque()
        self._backlog = bytearray()
        self._refusing = False
        self._closed = False
        self._flush_lock = threading.Lock()
        self._topic_lock = threading.Lock()
        self._topics: dict[str, Topic] = {}
        self._reported_drops: dict[str, int] = {}
        self._last_flush = time.monotonic()
        self._last_t_ns = 0
        self._writer_gone = ""
        self._report: dict[str, Any] | None = None  # the writer's last word, once it ended
        self._failure_raised = False
        self._next_check = 0.0
        self._ready = False
        self._stats: RecorderStats | None = None
        # with a live view of a run that has a tuner (``tunable``), the reverse channel of its
        # parameters (recording.tune_wire): the live view offers parameters only then
        self._tune_socket: socket.socket | None = None
        writer_end: socket.socket | None = None
        if self.options.live and tunable:
            self._tune_socket, writer_end = socket.socketpair()
        self._port_server: PortServer | None = None
        # with a claim (hil.core.recording.output), the writer writes the first file to the
        # claim's staging file, whose open descriptor it inherits
        first_fd = claim.fd if claim is not None else None
        tune_fd = writer_end.fileno() if writer_end is not None else None
        writer_options = {
            "path": self.path, "chunk_size": chunk_size, "flush_interval_s": flush_interval_s,
            "chunk_span_s": chunk_span_s,
            "profile": profile, "split_duration_s": self.options.split_duration_s,
            "split_size_mb": self.options.split_size_mb,
            # in real time a late writer costs a backlog, a late emulator a fault; in lockstep
            # the loop waits for the writer, so it must not be held back
            "yield_cpu": not wait_when_full,
            "live": self.options.live, "live_rates": self.options.live_rates,
            "live_remote_tuning": self.options.live_remote_tuning,
            "tune_fd": tune_fd, "first_fd": first_fd,
            "staging": claim.staging if claim is not None and first_fd is not None else None,
        }
        self._inline: InProcessWriter | None = None
        if self.options.in_process:
            self._inline = self._start_inline(writer_options)
        else:
            self._process = self._start_writer(
                writer_options, [fd for fd in (tune_fd, first_fd) if fd is not None])
            assert self._process.stdin is not None
            self._fd = self._process.stdin.fileno()
            with contextlib.suppress(OSError):  # a bigger pipe absorbs a slow writer longer
                fcntl.fcntl(self._fd, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
            os.set_blocking(self._fd, False)
        if writer_end is not None:
            writer_end.close()
        self.events = self.topic(EVENTS_TOPIC, EVENT_SCHEMA)

    def _start_inline(self, options: dict[str, Any]) -> InProcessWriter:
        """The in-process writer (lockstep only, no live view: :meth:`_check_in_process`)."""
        from hil.core.recording.in_process import InProcessWriter

        inline = InProcessWriter(options)
        if inline.error:
            self._writer_gone = "the writer failed to start"
        return inline

    def _check_in_process(self) -> None:
        """In-process recording is for lockstep (in real time its encoding would be the
        loop's) and has no live view (the writer process serves it)."""
        if not self.wait_when_full:
            raise HilError("in-process recording is for lockstep sessions: a real-time loop "
                           "hands its records to a writer process")
        if self.options.live:
            raise HilError("in-process recording has no live view: the writer process "
                           "serves it")

    @staticmethod
    def _start_writer(options: dict[str, Any], pass_fds: list[int]) -> ForkedWriter:
        """The writer process, forked by this process's fork server
        (:mod:`hil.core.recording.writer_fork`)."""
        from hil.core.recording.writer_fork import start_writer

        try:
            return start_writer(options, pass_fds)
        except OSError as exc:
            raise RecordingError(f"{options['path']}: the writer process could not start "
                                 f"({exc})") from None

    def serve_parameters(self, port: Any) -> None:
        """Answer the live view's parameter requests from ``port`` (the run's tuner: its
        ``specs()`` and ``request(name, value, client, timeout_s)``); nothing without a live
        view. Once per session."""
        if self._tune_socket is not None and self._port_server is None:
            from hil.core.recording.tune_wire import PortServer

            self._port_server = PortServer(self._tune_socket, port)

    @property
    def writer_pid(self) -> int | None:
        """The writer process's id (None: the session is written in this process)."""
        return None if self._inline is not None else self._process.pid

    def wait_ready(self, timeout_s: float = WRITER_START_TIMEOUT_S) -> None:
        """Wait until the writer process has started (imports done, file open), so that its
        start-up does not compete with the first ticks of a real-time loop."""
        if self._ready:
            return
        if self._inline is not None:
            if self._inline.error:
                raise RecordingError(f"{self.path}: the writer failed to start "
                                     f"({self._inline.error})")
            self._ready = True
            return
        line, timed_out = self._read_writer(timeout_s, line=True)
        if timed_out:
            raise RecordingError(f"{self.path}: the writer process did not start within "
                                f"{timeout_s:g} s")
        if line != b"ready\n":
            self._process.kill()
            raise RecordingError(f"{self.path}: the writer process failed to start "
                                f"({line.decode(errors='replace').strip() or 'no output'})")
        self._ready = True

    def _read_writer(self, timeout_s: float, *, line: bool) -> tuple[bytes, bool]:
        """The writer's standard output up to a newline (``line``) or to its end, and whether
        ``timeout_s`` ran out first (the writer is then killed)."""
        assert self._process.stdout is not None
        fd = self._process.stdout.fileno()
        deadline = time.monotonic() + timeout_s
        out = bytearray()
        while not (line and out.endswith(b"\n")):
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select([fd], [], [], remaining)[0]:
                self._process.kill()
                return bytes(out), True
            chunk = os.read(fd, 64 if line else 1 << 16)
            if not chunk:
                break
            out += chunk
        return bytes(out), False

    # -- producer side -------------------------------------------------------------------
    def topic(self, name: str, schema: dict[str, Any], *, encoding: str | None = None,
              high_rate: bool = False) -> Topic:
        """Register (or get) a topic with its JSON Schema.

        ``encoding``: ``json`` or ``cdr``; by default the session's choice for the topic
        (``RecordingOptions.topic_encodings``), else its high-rate encoding when
        ``high_rate``, else JSON. A topic that CDR cannot express stays JSON unless CDR was
        asked for by name.
        """
        with self._topic_lock:
            existing = self._topics.get(name)
            if existing is not None:
                return existing
            chosen = encoding or self.options.topic_encodings.get(name) or (
                self.options.high_rate_encoding if high_rate else "json")
            if chosen not in ENCODINGS:
                raise HilError(f"topic {name}: encoding {chosen!r} is not one of "
                               f"{', '.join(ENCODINGS)}")
            if chosen == "cdr":
                try:
                    fields_of(schema)
                except CdrError as exc:
                    if encoding or name in self.options.topic_encodings:
                        raise HilError(f"topic {name}: cannot be recorded as CDR: {exc}") from None
                    chosen = "json"
            topic = Topic(self, name, len(self._topics), chosen)
            self._topics[name] = topic
            self._queue.append(("topic", topic.channel_key, name, schema, chosen))
            return topic

    def rows(self, topics: tuple[Topic, ...]) -> TopicRows:
        """``topics`` logged together, one row each, in one hand-over (:class:`TopicRows`)."""
        return TopicRows(self, topics)

    def columns(self, topic: Topic) -> ColumnTopic:
        """``topic``'s messages built in the writer from rows (:class:`ColumnTopic`)."""
        return ColumnTopic(self, topic)

    def event(
        self, t_ns: int, kind: str, message: str, level: str = "info", source: str = "", **data: Any
    ) -> None:
        """Record an event on ``/events``."""
        self.events.log(
            t_ns, {"level": level, "source": source, "kind": kind, "message": message, "data": data}
        )

    def metadata(self, name: str, data: dict[str, str]) -> None:
        """Add a metadata record (string to string map)."""
        self._queue.append(("metadata", name, dict(data)))

    def attachment(self, name: str, data: bytes, media_type: str, t_ns: int = 0) -> None:
        """Attach a file (e.g. the configuration)."""
        self._queue.append(("attachment", name, bytes(data), media_type, t_ns))

    def dropped(self) -> dict[str, int]:
        return {name: t.dropped for name, t in self._topics.items() if t.dropped}

    def keep_off_cpu(self, cpu: int) -> None:
        """Move the writer process, every thread of it, off ``cpu`` (the loop's core)."""
        if self._inline is None:
            keep_process_off_cpu(self._process.pid, cpu)

    # -- hand-over -----------------------------------------------------------------------
    def flush_if_due(self) -> None:
        """The loop's per-tick call: hand the queue over every ``flush_every_s`` at most.

        Raises :class:`RecordingError` (once) when the writer process has failed or is gone:
        the session is no longer recorded, so the run must stop."""
        now = time.monotonic()
        if self._queue and now - self._last_flush >= self.flush_every_s:
            self.flush()
        if now >= self._next_check and not self._writer_gone and self._inline is None:
            self._next_check = now + WRITER_CHECK_EVERY_S
            if self._process.poll() is not None:
                self._writer_gone = "the writer process ended"
        if self._writer_gone and not self._failure_raised:
            self._failure_raised = True
            raise RecordingError(f"recording failed: {self.failure}: the run stopped")

    @property
    def failure(self) -> str | None:
        """Why the session is no longer recorded (None: it is): the writer's own reason
        (``No space left on device``...) once it has ended, else how it ended."""
        if not self._writer_gone:
            return None
        if self._inline is not None:
            return self._inline.error or self._writer_gone
        if self._stats is None and self._report is None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                self._process.wait(timeout=1.0)
            if self._process.returncode is not None:
                self._report = self._parse_result(self._writer_report())
        report = self._report or {}
        return str(report.get("error") or self._writer_gone)

    def flush(self) -> None:
        """Hand everything queued to the writer process (waits only in lockstep)."""
        with self._flush_lock:
            self._last_flush = time.monotonic()
            queue = self._queue
            records = [queue.popleft() for _ in range(len(queue))]
            if records:
                last = records[-1]
                if isinstance(last[0], int | tuple):  # a message, or a topic group's
                    self._last_t_ns = last[1]
                self._add_drop_report(records)
                if self._writer_gone:
                    self._count_lost(records)
                elif self._inline is not None:
                    self._write_inline(self._inline, records)
                else:
                    self._backlog += encode_frame(records)
            if self._inline is None:
                self._send(block=self.wait_when_full)
            else:
                self._refusing = self._closed or bool(self._writer_gone)

    def _write_inline(self, inline: InProcessWriter, records: list[tuple[Any, ...]]) -> None:
        """``records`` written in this process; on a failure, the rest counted lost."""
        written = inline.apply(records)
        if inline.error:
            self._writer_gone = "the session could not be written"
            self._count_lost(records[written:])

    def _add_drop_report(self, records: list[tuple[Any, ...]]) -> None:
        dropped = self.dropped()
        if dropped != self._reported_drops:
            self._reported_drops = dropped
            records.append(("drops", self._last_t_ns, dropped))

    def _send(self, block: bool) -> None:
        backlog = self._backlog
        while backlog and not self._writer_gone:
            try:
                written = os.write(self._fd, backlog)
            except BlockingIOError:
                written = 0
            except OSError as exc:  # BrokenPipeError: the writer process died
                self._writer_gone = f"the writer process is gone ({exc.strerror or exc})"
                self._count_lost([r for records in FrameDecoder().feed(bytes(backlog))
                                  for r in records])
                backlog.clear()
                break
            del backlog[:written]
            if written == 0:
                if not block:
                    break
                select.select([], [self._fd], [], 0.1)
        self._refusing = self._closed or bool(self._writer_gone) or (
            len(backlog) > self.max_backlog_bytes)

    def _count_lost(self, records: list[tuple[Any, ...]]) -> None:
        by_key = {t.channel_key: t for t in self._topics.values()}
        for record in records:
            kind = record[0]  # a message's key, a topic group's keys, a column message's
            keys = (record[1],) if kind == "message" else kind if type(kind) is tuple else (kind,)
            for key in keys:
                if isinstance(key, int) and key in by_key:
                    by_key[key].dropped += 1

    # -- lifecycle -------------------------------------------------------------------------
    def close(self) -> RecorderStats:
        """Hand over everything queued, let the writer finish the file; return what happened.

        Raises :class:`RecordingError` when the writer failed: the message names the cause and
        how many messages the file holds (counted in the file, the true count)."""
        if self._stats is not None:
            return self._stats
        self._queue.append(("close",))
        self.flush()
        self._closed = self._refusing = True
        if self._inline is not None:
            self._report = self._inline.close()
        else:
            self._send(block=True)
            assert self._process.stdin is not None
            with contextlib.suppress(OSError):
                self._process.stdin.close()
            if self._report is None:
                self._report = self._parse_result(self._writer_report())
        self._close_parameters()
        result = self._report
        drops = self.dropped()
        self._stats = RecorderStats(
            messages_written=int(result.get("messages_written", 0)), messages_dropped=drops,
            chunks_flushed=int(result.get("chunks_flushed", 0)),
            bytes_written=int(result.get("bytes_written", 0)),
            files=list(result.get("files", [])),
        )
        if result.get("error") or self._writer_gone:
            failure = result.get("error") or self.failure
            lost = sum(drops.values())
            raise RecordingError(
                f"recording failed: {failure}; {recorded_messages(self.path, self.options)} "
                f"message(s) recorded in {self.options.first_file(self.path)}"
                + (f", {lost} later message(s) lost" if lost else ""))
        return self._stats
    def _close_parameters(self) -> None:
        if self._port_server is not None:
            self._port_server.close()
        elif self._tune_socket is not None:
            self._tune_socket.close()
        self._tune_socket = None

    def _writer_report(self) -> bytes:
        """The writer's standard output until it exits (killed after a generous timeout);
        its last line is the JSON report."""
        out, _timed_out = self._read_writer(WRITER_CLOSE_TIMEOUT_S, line=False)
        self._process.wait()
        assert self._process.stdout is not None
        self._process.stdout.close()
        return out

    def _parse_result(self, out: bytes) -> dict[str, Any]:
        lines = out.decode(errors="replace").strip().splitlines()
        try:
            result = json.loads(lines[-1]) if lines else {}
        except ValueError:
            result = {}
        if not result:
            code = self._process.returncode
            result = {"error": f"the writer process was killed ({signal.Signals(-code).name})"
                      if code is not None and code < 0 else
                      f"the writer process exited with status {code} and no report"}
        return dict(result)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def recorded_messages(path: str, options: RecordingOptions) -> int:
    """How many messages the session at ``path`` holds, counted by reading it (a file its
    writer could not finish included)."""
    from hil.core.recording.reader import read_session

    try:
        return sum(read_session(options.first_file(path)).topic_counts.values())
    except HilError:
        return 0
