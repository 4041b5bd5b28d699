"""A virtual null-modem cable: two pseudo-terminals whose traffic a thread copies across.

What ``socat pty,raw pty,raw`` does, with ``os.openpty`` only: each end is a real
``/dev/pts/N`` that pyserial (and so pymodbus) opens like a serial port. A pty moves bytes
as fast as the kernel copies them; give ``baudrate`` to deliver every chunk only after the
time it would take on a real line (10 bits per byte for 8N1, 11 with parity), so round trips
measured through the cable include the wire time of the frames.

A noisy line is a fault the cable plays (:mod:`hil.emulators.faults`, kind ``noise``, on the
cable's time: seconds since it was made, or what ``now`` says): while one is on, each byte
crossing it, either way, has one bit flipped with probability ``rate``, the bytes and bits drawn
from ``seed`` (the same bytes through the same cable are flipped the same way). ``carried`` and
``flipped`` count the bytes each way.
"""

from __future__ import annotations

import contextlib
import math
import os
import random
import select
import threading
import time
import tty
from collections.abc import Callable, Iterable

from hil.emulators.faults import Fault, FaultSchedule, for_emulator


class NullModem:
    """Two connected serial ports: ``ports[0]`` <-> ``ports[1]``. Use as a context manager.
    ``faults``: line faults (``noise``) on the cable's time, ``now()`` (default: seconds since
    it was made); each is told to ``on_fault`` as it starts."""

    def __init__(self, baudrate: float | None = None, bits_per_byte: int = 10,
                 faults: Iterable[Fault] = (),
                 on_fault: Callable[[str], None] | None = None,
                 now: Callable[[], float] | None = None) -> None:
        self.byte_time_s = bits_per_byte / baudrate if baudrate else 0.0
        started = time.monotonic()
        self.faults = FaultSchedule(for_emulator(faults, "line"),
                                    now or (lambda: time.monotonic() - started), on_fault)
        #: bytes copied and bytes flipped, each way: [0] ports[0] -> ports[1], [1] back
        self.carried, self.flipped = [0, 0], [0, 0]
        self._noise = {(id(f), way): Noise(f, way) for f in self.faults.faults for way in (0, 1)}
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
            threading.Thread(target=self._copy, args=(self._masters[a], self._masters[b], a),
                             name=f"null-modem-{a}{b}", daemon=True)
            for a, b in ((0, 1), (1, 0))
        ]
        for thread in self._threads:
            thread.start()

    def _copy(self, source: int, sink: int, way: int) -> None:
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
            data = self._through_the_line(data, way)
            if self.byte_time_s:
                line_free_at = max(time.monotonic(), line_free_at) + len(data) * self.byte_time_s
                delay = line_free_at - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            with contextlib.suppress(OSError):  # nobody on the other end: lost, as on a wire
                os.write(sink, data)

    def _through_the_line(self, data: bytes, way: int) -> bytes:
        """``data`` as it arrives at the far end: the noise on now flips some of its bits."""
        self.carried[way] += len(data)
        noisy = self.faults.active("noise")
        if not noisy:
            return data
        out = bytearray(data)
        for fault in noisy:
            flips = self._noise[(id(fault), way)].flip(out)
            for _ in range(flips):
                self.faults.hit(fault)
            self.flipped[way] += flips
        return bytes(out)

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


class Noise:
    """One ``noise`` fault on one way of the line: the bytes it flips, one bit each, drawn from
    its seed (the gaps between flipped bytes are geometric: each byte is flipped with
    probability ``rate``, whatever the chunks the bytes come in)."""

    def __init__(self, fault: Fault, way: int) -> None:
        self.rate: float = fault.params["rate"]
        self._random = random.Random(f"{fault.params['seed']}:{way}")
        self._skip = self._gap()

    def _gap(self) -> int:
        """Bytes that pass untouched before the next flipped one."""
        if self.rate >= 1:
            return 0
        return int(math.log(1.0 - self._random.random()) / math.log(1.0 - self.rate))

    def flip(self, data: bytearray) -> int:
        """Flip the chosen bits of ``data`` in place; how many bytes were flipped."""
        flips, at = 0, self._skip
        while at < len(data):
            data[at] ^= 1 << self._random.randrange(8)
            flips += 1
            at += 1 + self._gap()
        self._skip = at - len(data)
        return flips
