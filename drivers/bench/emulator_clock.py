"""A lockstep master's side of hil's bench emulator (the wire tables:
:mod:`hil.protocols.bench_clock`): :func:`identify` tells hil's emulator from a real bench by
its Modbus device identification, :class:`EmulatorClock` gives the emulator the master's time,
in numbered requests: one asked again (a frame lost or garbled on the line) steps the plant
once, and its answer names the request it answers.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

from hil.drivers.bench.modbus import DeviceError, LinkError, ModbusLink
from hil.drivers.errors import DriverError, ForeignMasterError
from hil.protocols.bench_clock import (
    CLOCK_UNIT,
    CONTROL_REGISTER,
    HELD_BY_ANOTHER,
    KEEPS_WALL_CLOCK,
    PRODUCT_CODE,
    STEP_REGISTER,
    TIME_REGISTER,
    VENDOR,
    next_number,
    same_major_revision,
    step_words,
    time_of,
)


@dataclass(frozen=True)
class Identity:
    """A device's basic identification objects (FC43/MEI 14)."""

    vendor: str
    product_code: str
    revision: str

    @property
    def is_hil_emulator(self) -> bool:
        return self.vendor == VENDOR and self.product_code == PRODUCT_CODE

    @property
    def speaks_our_clock(self) -> bool:
        """hil's emulator of this master's time protocol (its major revision)."""
        return self.is_hil_emulator and same_major_revision(self.revision)

    def __str__(self) -> str:
        """``VENDOR PRODUCT_CODE REVISION``, the objects the device gave."""
        return " ".join(filter(None, (self.vendor, self.product_code, self.revision)))


def identify(link: ModbusLink, unit: int, timeout_s: float) -> Identity | None:
    """The identity of the device at ``unit``, asked once, waiting up to ``timeout_s`` (a busy
    machine may be slow to answer: a lost answer would make a lockstep run a wall-clock one;
    over a serial line the question is asked again every request timeout within it);
    None when it gives none (an exception, as most real devices answer, or nothing). A
    question the device did not answer is no retry of the bench's polls: ``link.retries`` is
    left as it was."""
    retries = link.retries
    try:
        with link.patient(timeout_s):
            objects = link.read_identification(unit)
    except (DeviceError, LinkError):
        return None
    finally:
        link.retries = retries

    def text(object_id: int) -> str:
        return objects.get(object_id, b"").decode("utf-8", "replace")

    return Identity(text(0), text(1), text(2))


class KeepsWallClockError(DriverError):
    """hil's bench emulator keeps its wall clock (``--clock wall``): it follows no master."""


class EmulatorClock:
    """A lockstep master's hold on the time of hil's bench emulator, over the bench's link (the
    same connection as the polls, so a step is done before the next poll is answered)."""

    def __init__(self, link: ModbusLink) -> None:
        self.link = link
        self._number = 0  # of the last time request

    def start(self, request_timeout_s: float) -> None:
        """A lockstep session: the emulator's plant starts again from t = 0 on this master's
        time. :class:`KeepsWallClockError` when the emulator keeps its wall clock,
        ``ForeignMasterError`` when another master holds its time."""
        ms = min(max(round(request_timeout_s * 1000), 1), 0xFFFF)
        try:
            self.link.write_register(CLOCK_UNIT, CONTROL_REGISTER, ms)
        except DeviceError as exc:
            url = self.link.spec.url
            if exc.code == KEEPS_WALL_CLOCK:
                raise KeepsWallClockError(
                    f"the bench emulator at {url} keeps its wall clock (hil emulate bench "
                    "--clock wall): this run follows the wall clock too, as against a real "
                    "bench") from None
            if exc.code == HELD_BY_ANOTHER:
                raise ForeignMasterError(
                    f"the bench emulator at {url} already follows another lockstep run's "
                    "time: one master at a time") from None
            raise

    def advance(self, t_ns: int) -> None:
        """The plant steps to ``t_ns`` (the master's time since its first tick); returns once
        the emulator has, and answered this request's number."""
        self._number = number = next_number(self._number)
        self.link.exchange_registers(
            CLOCK_UNIT, STEP_REGISTER, step_words(number, t_ns),
            f"time request {number} ({t_ns / 1e9:.2f} s) to the bench emulator",
            lambda words: words[0] == number)

    def post(self, t_ns: int) -> None:
        """The plant steps to ``t_ns``, the answer not waited for (over TCP: the emulator
        steps while this side works, and answers its next request after the step); where
        that cannot be, as :meth:`advance`."""
        number = next_number(self._number)
        if self.link.post_exchange(CLOCK_UNIT, STEP_REGISTER, step_words(number, t_ns)):
            self._number = number
        else:
            self.advance(t_ns)

    def plant_time_ns(self) -> int:
        return time_of(self.link.read_registers(CLOCK_UNIT, TIME_REGISTER, 4))

    def state(self) -> int:
        """What the emulator's time follows: ``ON_WALL_CLOCK``, ``ON_MASTER_TIME`` or
        ``WAITING_FOR_MASTER`` (:mod:`hil.protocols.bench_clock`)."""
        return self.link.read_registers(CLOCK_UNIT, CONTROL_REGISTER, 1)[0]

    def release(self) -> None:
        """Let go of the emulator's time (best effort: a gone peer has let go already). On the
        link's own connection while it is open: a new one could reach the emulator before it
        saw the old one close, and be refused as another master (the emulator then lets go
        when its grace after the close runs out). The link's requests wait its own timeout
        after: the emulator keeps the wall clock again."""
        try:
            with contextlib.suppress(DriverError):
                self.link.write_register(CLOCK_UNIT, CONTROL_REGISTER, 0)
        finally:
            self.link.let_go()
