"""A virtual null-modem cable: two pseudo-terminals whose traffic a thread copies across.

What ``socat pty,raw pty,raw`` does, with ``os.openpty`` only: each end is a real
``/dev/pts/N`` that pyserial (and so pymodbus) opens like a serial port. A pty moves bytes
as fast as the kernel copies them; give ``baudrate`` to deliver every chunk only after the
time it would take on a real line (10 bits per byte for 8N1, 11 with parity), so round trips
measured through the cable include the wire time of the frames.
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty


class NullModem:
    """Two connected serial ports: ``ports[0]`` <-> ``ports[1]``. Use as a context manager."""

    def __init__(self, baudrate: float | None = None, bits_per_byte: int = 10) -> None:
        self.byte_time_s = bits_per_byte / baudrate if baudrate else 0.0
        self._masters: list[int] = []
        self._slaves: list[int] = []
        for _ in range(2):
            master, slave = os.openpty()
            tty.setraw(slave)  # no echo, no line editing before pyserial opens it
            self._masters.append(master)
            self._slaves.append(slave)
        self.ports = (os.ttyname(self._slaves[0]), os.ttyname(self._slaves[1]))
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._copy, args=(self._masters[a], self._masters[b]),
                             name=f"null-modem-{a}{b}", daemon=True)
            for a, b in ((0, 1), (1, 0))
        ]
        for thread in self._threads:
            thread.start()

    def _copy(self, source: int, sink: int) -> None:
        line_free_at = 0.0
        while not self._stop.is_set():
            ready, _, _ = select.select([source], [], [], 0.05)
            if not ready:
                continue
            try:
                data = os.read(source, 4096)
            except OSError:  # the other side closed: wait for it to reopen
                time.sleep(0.01)
                continue
            if self.byte_time_s:
                line_free_at = max(time.monotonic(), line_free_at) + len(data) * self.byte_time_s
                delay = line_free_at - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            with contextlib.suppress(OSError):  # nobody on the other end: lost, as on a wire
                os.write(sink, data)

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2)
        for fd in self._masters + self._slaves:
            os.close(fd)
        self._masters, self._slaves = [], []

    def __enter__(self) -> NullModem:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
