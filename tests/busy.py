"""A busy machine on demand: one busy process per core, niced as an ordinary CI neighbour is
(``nice 10``), each bounded in time by itself, so a test can prove that what it checks holds
on a loaded machine, not only on a quiet one.

::

    with busy_machine():
        ...  # both cores are busy while this runs

The processes are killed when the block ends; each also stops by itself after ``bound_s``
(a test killed mid-way leaves nothing spinning). ``python tests/busy.py SECONDS`` keeps the
machine busy that long, e.g. beside a whole ``make test``.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator

NICE = 10
#: what each busy process runs: spin until its time is up
SPIN = "import time, sys\nend = time.monotonic() + float(sys.argv[1])\n" \
       "while time.monotonic() < end:\n    pass\n"


@contextlib.contextmanager
def busy_machine(bound_s: float = 300.0, processes: int | None = None) -> Iterator[list[int]]:
    """``processes`` busy processes (default: one per core) for the block, at most
    ``bound_s``; their pids."""
    count = processes or os.cpu_count() or 2
    spinning = [subprocess.Popen([sys.executable, "-c", SPIN, str(bound_s)],
                                 preexec_fn=lambda: os.nice(NICE),
                                 stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
                for _ in range(count)]
    try:
        yield [p.pid for p in spinning]
    finally:
        for process in spinning:
            process.kill()
        for process in spinning:
            process.wait(timeout=10)


def busy_now(pids: list[int]) -> bool:
    """Whether every one of ``pids`` is still spinning (running or runnable)."""
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as f:
                state = f.read().rpartition(")")[2].split()[0]
        except OSError:
            return False
        if state != "R":
            return False
    return True


if __name__ == "__main__":  # python tests/busy.py SECONDS: a busy machine while something runs
    import time

    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 600.0
    with busy_machine(bound_s=seconds):
        time.sleep(seconds)
