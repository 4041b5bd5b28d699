"""The session's writer in the loop's own process: for lockstep runs where a writer process
costs more than it gives, a sweep's trials above all (every core already runs a trial, and a
writer process per trial halves what each gets).

:class:`InProcessWriter` does what the writer process (:mod:`hil.core.recording.writer`) does,
with the same code, on the records the recorder hands it at each flush: the same
:class:`~hil.core.recording.writer.SessionWriter` encodes them into the same
:class:`~hil.core.recording.mcap_series.McapSeries`, a chunk closes at least every
``flush_interval_s`` of wall time and every ``chunk_span_s`` of session time, and
:meth:`InProcessWriter.close` finishes the file with the same summary, index and final
metadata. What the process gives and this does not: the file finished by another process
when the loop's is killed (a SIGKILL leaves it cut after its last chunk, which the reader
recovers with counts like any damaged session), and the loop kept free of the encoding, which
only lockstep can afford (the recorder refuses this writer in real time). Its chunks are
compressed at zstd level 1 rather than the writer process's 9, since the trial itself pays
for the compression here: level 3 took a fifth of level 9's time for a file about 1 % larger,
and level 1 takes 2 % less of a 20 s MPC trial's CPU than level 3 for a file 2 % larger.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from typing import Any

from hil.core.recording.writer import SessionWriter, describe_failure, finish, open_series

#: a 20 s MPC trial's CPU at zstd level 1: 2.585 s against 2.647 s at the default
#: level 3 (medians of 8 alternated trials), its file 13.38 MB against 13.09 MB
ZSTD_LEVEL = 1


class InProcessWriter:
    """Writes a session's records as they are handed over, in this process. ``options``:
    the writer process's (the recorder's); its ``first_fd`` is duplicated, the claim keeps
    its own. A failure (the file cannot be opened or written) is kept in :attr:`error`
    and ends the writing: what was written stays in the file."""

    def __init__(self, options: dict[str, Any]) -> None:
        self.error = ""
        self.writer: SessionWriter | None = None
        self._flush_interval_s = float(options.get("flush_interval_s", 1.0))
        self._next_flush = time.monotonic() + self._flush_interval_s
        first_fd = options.get("first_fd")
        try:
            options = {**options, "zstd_level": ZSTD_LEVEL}
            if first_fd is not None:  # the series closes the descriptor it is given
                options["first_fd"] = os.dup(first_fd)
            self.writer = SessionWriter(open_series(options))
        except Exception as exc:
            self.error = describe_failure(exc)

    def apply(self, records: Sequence[tuple[Any, ...]]) -> int:
        """Write ``records`` in order, in one pass; return how many were written (all of
        them unless the writing failed: :attr:`error` then says why;
        :meth:`SessionWriter.apply_all` says what the count is then)."""
        writer = self.writer
        if writer is None or self.error:
            return 0
        try:
            writer.apply_all(records)
            if time.monotonic() >= self._next_flush:
                writer.series.flush()
                self._next_flush = time.monotonic() + self._flush_interval_s
        except Exception as exc:
            self.error = describe_failure(exc)
        return writer.applied

    def close(self) -> dict[str, Any]:
        """Finish the file; the writer process's report (``messages_written``, ``error``...)."""
        if self.writer is None:
            return {"messages_written": 0, "error": self.error, "closed": False}
        return finish(self.writer, self.error)
