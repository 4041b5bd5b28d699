"""Recording and reading sessions: everything between a loop's ``Topic.log`` and a session on
disk, and back.

Writing, on the loop's side:

* :mod:`~hil.core.recording.recording_options` - how a session is recorded (encoding,
  splitting, live view), light enough for the command line to import alone;
* :mod:`~hil.core.recording.output` - the session file claimed for one run: checked writable
  and locked before any device is opened;
* :mod:`~hil.core.recording.recorder` - the loop side: topics queue their messages, the queue
  goes to the writer process as frames, with back-pressure and counted drops;
* :mod:`~hil.core.recording.record_stream` - the framed byte stream from the loop process to
  its writer process.

Writing, in the writer process:

* :mod:`~hil.core.recording.writer` - the writer process: encoding, compression and file I/O
  off the loop's interpreter; finishes the file however the loop ends;
* :mod:`~hil.core.recording.writer_fork` - the writer processes forked from a server per
  loop process, each still the loop process's child;
* :mod:`~hil.core.recording.cdr` - the compact CDR encoding of flat topics, with ``ros2msg``
  schemas derived from their JSON Schemas;
* :mod:`~hil.core.recording.mcap_series` - one session as one MCAP file or a split series;
* :mod:`~hil.core.recording.mcap_writer` - the indexed, chunked MCAP writer with a zstd level;
* :mod:`~hil.core.recording.live` - the live view, the writer's second sink: the session's
  topics over the Foxglove WebSocket protocol.

Reading:

* :mod:`~hil.core.recording.reader` - a session (one file or a split series, finished,
  truncated or damaged) read back, with what could not be read;
* :mod:`~hil.core.recording.mcap_walk` - the record-by-record MCAP walk that checks CRCs and
  accounts for damage;
* :mod:`~hil.core.recording.chunk_messages` - a chunk's messages as arrays, found by their
  record heads, no object per message;
* :mod:`~hil.core.recording.message_store` - a session's messages as read: one buffer, and per
  topic each message's log time and place in it;
* :mod:`~hil.core.recording.cdr_columns` - a CDR topic decoded field by field over all its
  messages at once (numpy), each field when asked for;
* :mod:`~hil.core.recording.replay` - a recorded session streamed through the live view as if
  it ran now.

The session that ties a recorder to a clock and a loop is :mod:`hil.core.session`; summaries,
plots and identification built on the reader are :mod:`hil.core.report` and
:mod:`hil.core.identify`. Like the rest of :mod:`hil.core`, this package names no
application, driver or emulator.
"""
