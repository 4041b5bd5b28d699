"""What the emulated bench's time follows (``hil emulate bench --clock``), and the clock's unit
on the wire (the tables: :mod:`hil.protocols.bench_clock`).

* ``auto`` - the wall clock, until a lockstep master on the wire takes the time; the master's
  time then, until it lets go (writes 0 to ``CONTROL``, or its connection ends and it is not
  back within :data:`GRACE_S`); then the wall clock again, from where the master left the
  plant;
* ``wall`` - the wall clock always: a master that asks is refused (exception 1), so it knows;
* ``master`` - a master's time only: the plant waits until a master takes it, and again after
  it lets go.

A master's session starts the plant and its fault schedule again from t = 0, so a lockstep
session is the same whatever the emulator did before. On the master's time, each numbered
``STEP`` request steps the plant, in the connection's thread, before its answer and before the
next request of that connection (the master's next poll sees that step), as
:class:`hil.bench.emulator_time.PlantStepTask` steps an emulator in the loop's process. A
master whose connection ends (it dropped it after a failed request, or a ``close`` fault did)
keeps the time for :data:`GRACE_S`: its next ``TIME`` write, on its next connection, takes it
back, and no wall-clock step comes between. A step request carries a number: the same
number again (the master asked again: the request or its answer was lost on the line) is
answered as it was, without a step, so no retry moves the plant twice.
"""

from __future__ import annotations

import math
import socket
import struct
import threading
import time
from collections.abc import Callable
from typing import Protocol

from hil.emulators.bench.modbus_server import (
    ILLEGAL_ADDRESS,
    ILLEGAL_FUNCTION,
    ILLEGAL_VALUE,
    exception_pdu,
)
from hil.emulators.bench.plant import BenchPlant
from hil.protocols.bench_clock import (
    CLOCK_REGISTERS,
    CLOCK_UNIT,
    CLOCKS,
    CONTROL_REGISTER,
    HELD_BY_ANOTHER,
    KEEPS_WALL_CLOCK,
    ON_MASTER_TIME,
    ON_WALL_CLOCK,
    STEP_REGISTER,
    STEP_REGISTERS,
    WAITING_FOR_MASTER,
    step_words,
    time_of,
    time_words,
)

#: how often the wall-clock thread looks whether a master let go
HELD_POLL_S = 0.02
#: the request timeout a master that never said its own is taken to have
DEFAULT_TIMEOUT_S = 0.1
#: how long a master whose connection ended keeps the time (it reconnects within ms)
GRACE_S = 1.0
#: the most plant time one ``TIME`` write may ask for (a master asks for one tick); a time
#: further ahead is refused (exception 3) rather than stepped for hours
MAX_TIME_STEP_S = 60.0


class Stepped(Protocol):
    """What the timekeeper moves (:class:`~hil.emulators.bench.server.EmulatedBench`)."""

    plant: BenchPlant

    def step(self, steps: int = 1) -> object:
        """One plant step (and what the fault schedule does to it)."""
        ...

    def restart(self) -> None:
        """The plant and its fault schedule as they were built."""
        ...


class Timekeeper:
    """The plant's time: the wall clock (a thread) or a lockstep master's (the clock's unit,
    :data:`~hil.protocols.bench_clock.CLOCK_UNIT`, served ahead of any fault). ``on_change``
    hears one line each time a master takes the time, lets go or is refused."""

    unit = CLOCK_UNIT

    def __init__(self, bench: Stepped, clock: str,
                 on_change: Callable[[str], None] | None = None) -> None:
        if clock not in CLOCKS:
            raise ValueError(f"clock must be one of {', '.join(CLOCKS)}, got {clock!r}")
        self.bench, self.clock = bench, clock
        self.on_change = on_change or (lambda _line: None)
        self._lock = threading.Lock()
        self._held = False            # on a master's time
        self._owner: object = None    # its connection (None: the one it comes back on)
        self._orphaned_at: float | None = None  # monotonic: when its connection ended
        self._timeout_s = DEFAULT_TIMEOUT_S
        self._k0 = 0                  # the plant's step at the master's time 0
        self._step = step_words(0, 0)  # the last step request's number and answer
        self._wall: tuple[float, int] | None = None  # (monotonic, plant step) at its start
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- the wall clock ---------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="bench-plant", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                wait_s = self._follow_wall_clock()
            self._stop.wait(wait_s)

    def _follow_wall_clock(self) -> float:
        """Step the plant to the wall clock's time (none while a master holds it or one is
        awaited); the seconds until the next step is due. A master gone for longer than
        :data:`GRACE_S` lets go here."""
        orphaned = self._orphaned_at
        if self._held and orphaned is not None and time.monotonic() - orphaned > GRACE_S:
            self._let_go("closed its connection")
        if self._held or self.clock == "master":
            self._wall = None  # the wall clock starts afresh when the master lets go
            return HELD_POLL_S
        plant, now = self.bench.plant, time.monotonic()
        if self._wall is None:
            self._wall = (now, plant.k)
        t0, k0 = self._wall
        self.bench.step(max(0, k0 + math.floor((now - t0) / plant.dt) - plant.k))
        return max(t0 + (plant.k - k0 + 1) * plant.dt - time.monotonic(), 0.0)

    # -- the master's time ------------------------------------------------------------------
    @property
    def master_timeout_s(self) -> float | None:
        """While a master holds the time: its request timeout; else None."""
        return self._timeout_s if self._held else None

    def state(self) -> int:
        if self._held:
            return ON_MASTER_TIME
        return WAITING_FOR_MASTER if self.clock == "master" else ON_WALL_CLOCK

    def answer(self, pdu: bytes, peer: object) -> bytes:
        """The clock's unit: FC03 reads, FC06 ``CONTROL``, FC23 ``STEP``."""
        code = pdu[0]
        if code not in (3, 6, 23):
            return exception_pdu(code, ILLEGAL_FUNCTION)
        if len(pdu) < (10 if code == 23 else 5):
            return exception_pdu(code, ILLEGAL_VALUE)
        address, value = struct.unpack_from(">HH", pdu, 1)
        if code == 3:
            return self._read(address, value)
        if code == 6:
            if address != CONTROL_REGISTER:
                return exception_pdu(code, ILLEGAL_ADDRESS)
            error = self._control(value, peer)
            return exception_pdu(code, error) if error else pdu[:5]
        return self._step_request(pdu, peer)

    def _step_request(self, pdu: bytes, peer: object) -> bytes:
        """FC23 at ``STEP``: read 5 and write 5 registers there, the number not 0."""
        read_at, read_count, write_at, write_count, byte_count = struct.unpack_from(
            ">HHHHB", pdu, 1)
        if (read_at, write_at) != (STEP_REGISTER, STEP_REGISTER):
            return exception_pdu(23, ILLEGAL_ADDRESS)
        if (read_count, write_count, byte_count) != (STEP_REGISTERS, STEP_REGISTERS,
                                                     2 * STEP_REGISTERS) \
                or len(pdu) < 10 + 2 * STEP_REGISTERS:
            return exception_pdu(23, ILLEGAL_VALUE)
        number, *words = struct.unpack_from(f">{STEP_REGISTERS}H", pdu, 10)
        if number == 0:
            return exception_pdu(23, ILLEGAL_VALUE)
        answer = self._advance(number, time_of(words), peer)
        if isinstance(answer, int):
            return exception_pdu(23, answer)
        return bytes([23, 2 * STEP_REGISTERS]) + struct.pack(f">{STEP_REGISTERS}H", *answer)

    def _read(self, address: int, count: int) -> bytes:
        if not 1 <= count <= CLOCK_REGISTERS:
            return exception_pdu(3, ILLEGAL_VALUE)
        if address + count > CLOCK_REGISTERS:
            return exception_pdu(3, ILLEGAL_ADDRESS)
        plant = self.bench.plant
        words = [*time_words(round(plant.k * plant.dt * 1e9)), self.state(), *self._step]
        chosen = words[address:address + count]
        return bytes([3, 2 * count]) + struct.pack(f">{count}H", *chosen)

    def _refused(self, peer: object) -> int | None:
        """Why ``peer`` may not drive the time (an exception code), or None (under the
        lock)."""
        if self.clock == "wall":
            self.on_change(f"a lockstep master {_name(peer)} asked for the plant's time: "
                           "refused (--clock wall)")
            return KEEPS_WALL_CLOCK
        if self._held and self._owner is not None and self._owner is not peer:
            return HELD_BY_ANOTHER
        return None

    def _control(self, value: int, peer: object) -> int | None:
        """``CONTROL`` = N > 0: a session starts (request timeout N ms); 0: let go."""
        if not value:
            with self._lock:
                if self._held and self._owner not in (None, peer):
                    return HELD_BY_ANOTHER
                if self._held:
                    self._let_go("let go")
            return None
        with self._lock:
            error = self._refused(peer)
            if error:
                return error
            self.bench.restart()
            self._held, self._owner, self._orphaned_at = True, peer, None
            self._timeout_s, self._k0 = value / 1000, self.bench.plant.k
            self._step = step_words(0, 0)
        self.on_change(f"a lockstep master {_name(peer)} took the plant's time; the plant "
                       "starts again from t = 0")
        return None

    def _advance(self, number: int, t_ns: int, peer: object) -> list[int] | int:
        """Step request ``number``: the plant steps until it is at the master's time t (taking
        the time back first if its master lost its connection); the number and the plant's
        time since the master's time 0, or why not (an exception code). The number of the
        last step again is a retry: its answer again, no step. A t more than
        :data:`MAX_TIME_STEP_S` ahead of the plant is refused."""
        with self._lock:
            error = self._refused(peer)
            if error:
                return error
            if number != self._step[0]:
                plant = self.bench.plant
                steps = self._k0 + round(t_ns / 1e9 / plant.dt) - plant.k
                if steps * plant.dt > MAX_TIME_STEP_S:
                    return ILLEGAL_VALUE
                self._held, self._owner, self._orphaned_at = True, peer, None
                self.bench.step(max(0, steps))
                self._step = step_words(number, round((plant.k - self._k0) * plant.dt * 1e9))
            self._held, self._owner, self._orphaned_at = True, peer, None
            return list(self._step)

    def closed(self, peer: object) -> None:
        """A connection ended: if it was the master's, the master keeps the time for
        :data:`GRACE_S` (the wall-clock thread lets go after it)."""
        with self._lock:
            if self._held and self._owner is peer:
                self._owner, self._orphaned_at = None, time.monotonic()

    def _let_go(self, how: str) -> None:
        self._held, self._owner, self._orphaned_at = False, None, None
        then = "waits for a master" if self.clock == "master" else "follows the wall clock"
        self.on_change(f"the lockstep master {how} at plant time {self.bench.plant.t_s:.2f} s; "
                       f"the plant {then}")


def _name(peer: object) -> str:
    """Where a master is, as a line says it: ``at HOST:PORT`` (its connection) or ``on PORT``
    (the serial line)."""
    if isinstance(peer, socket.socket):
        try:
            host, port = peer.getpeername()[:2]
        except OSError:
            return "on a closed connection"
        return f"at {host}:{port}"
    return f"on {getattr(peer, 'port', peer)}"
