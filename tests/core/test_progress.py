"""The progress line is written from a thread of its own: a terminal that does not take it
(here a pipe nobody reads, full) holds up the line, never the loop."""

from __future__ import annotations

import contextlib
import os
import threading
import time

import pytest

from hil.core import progress
from hil.core.clock import SimClock
from hil.core.loop import FixedRateLoop, FunctionTask
from hil.core.progress import ProgressLine

pytestmark = pytest.mark.timeout(60)


def full_pipe() -> tuple[int, int]:
    """A pipe whose buffer is full: the next write to its write end blocks."""
    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    with contextlib.suppress(BlockingIOError):
        while True:
            os.write(write_end, b"." * 4096)
    os.set_blocking(write_end, True)
    return read_end, write_end


@pytest.mark.slow
def test_a_stream_that_blocks_holds_up_the_line_not_the_loop(monkeypatch):
    monkeypatch.setattr(progress, "REFRESH_S", 0.02)
    read_end, write_end = full_pipe()
    stream = os.fdopen(write_end, "w")
    line = ProgressLine("servo pid", 0.5, divisor=1, stream=stream)
    writer = line._writer

    def tick(t_ns: int) -> None:  # ticks as long as the line's refresh: it is due many times
        time.sleep(0.002)

    loop = FixedRateLoop(SimClock(), 1e-3, [FunctionTask("tick", read=tick), line],
                         handle_signals=False)
    loop.run(max_ticks=250)
    assert loop.ticks == 250 and writer.is_alive()  # the writer is stuck in its write
    taken = bytearray()

    def drain() -> None:
        while chunk := os.read(read_end, 65536):
            taken.extend(chunk)

    reader = threading.Thread(target=drain)
    reader.start()
    line.clear()
    stream.close()
    reader.join(timeout=10)
    os.close(read_end)
    shown = taken.decode().lstrip(".")
    assert shown.startswith("\rservo pid: ") and " of 0.5 s (" in shown
    assert shown.endswith("\r\x1b[K") and not writer.is_alive()

