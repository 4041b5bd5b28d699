"""Modbus answers into hil's bench driver: a peer over a real TCP socket and over a real
serial line (a pty pair) answers each request as hil's emulator would, then damages the
answer as the case says (bits flipped, cut, grown, replaced, another transaction's id, an
exception, the connection closed), while the driver opens the bench, polls it, switches a
relay, takes the emulator's time and goes to its safe state.

The rule for the driver: every call returns what it promises (floats, booleans) or raises a
:class:`~hil.drivers.errors.DriverError` of one line, within the bound; and a safe state the
driver reports done is done: the peer's relays are at their safe levels.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from hypothesis import strategies as st

from hil.bench.config import load_bench_config
from hil.bench.emulated import make_emulator
from hil.core.clock import SimClock
from hil.drivers.bench.emulator_clock import EmulatorClock, identify
from hil.drivers.bench.modbus import BusSpec, ModbusBenchDriver, ModbusLink
from hil.drivers.bench.safe_bench import SafeBench
from hil.drivers.errors import DriverError
from hil.emulators.bench.modbus_server import (
    GATEWAY_TARGET_FAILED,
    UnknownUnitError,
    crc16,
    exception_pdu,
    rtu_request_size,
)
from hil.emulators.bench.timekeeper import Timekeeper
from hil.emulators.null_modem import NullModem
from tests.fuzz.harness import Check, Target, bound, clear_error

TIMEOUT_S = 0.05  # the driver's wait per request: a cut answer costs this much, no more


@dataclass(frozen=True)
class Damage:
    """What the peer does to one answer: ``frame`` maps the right frame to what is sent
    (None: nothing, silence); ``close``: the connection is closed after it (TCP)."""

    frame: Callable[[bytes], bytes | None]
    close: bool = False
    label: str = ""

    def __repr__(self) -> str:
        return f"Damage({self.label}{', close' if self.close else ''})"


@st.composite
def damages(draw: st.DrawFn) -> Damage:
    how = draw(st.sampled_from(["right", "right", "bytes", "exception", "tid", "silence"]))
    close = draw(st.booleans())
    if how == "right":
        return Damage(lambda frame: frame, close, "right")
    if how == "silence":
        return Damage(lambda frame: None, close, "silence")
    if how == "exception":
        code = draw(st.sampled_from([1, 2, 3, 4, 5, 6, 10, 11]) | st.integers(0, 255))
        return Damage(lambda frame: frame[:-len(frame) + 7] + exception_pdu(frame[7], code)
                      if len(frame) > 7 else frame, close, f"exception {code}")
    if how == "tid":
        other = draw(st.integers(0, 0xFFFF))
        return Damage(lambda frame: struct.pack(">H", other) + frame[2:], close, f"tid {other}")
    # the same mutation, drawn once, for whichever frame it meets
    seed = draw(st.binary(min_size=0, max_size=24))
    mutate = draw(st.sampled_from(["flip", "cut", "grow", "replace"]))
    return Damage(lambda frame: _mutated(frame, mutate, seed), close, f"{mutate} {seed.hex()}")


def _mutated(frame: bytes, how: str, seed: bytes) -> bytes:
    if how == "flip":
        out = bytearray(frame)
        for i in range(0, len(seed) - 1, 2):
            out[seed[i] % len(out)] ^= seed[i + 1] or 1
        return bytes(out)
    if how == "cut":
        return frame[:seed[0] % len(frame)] if seed else b""
    if how == "grow":
        return frame + seed
    return seed


class Peer:
    """Answers Modbus requests as hil's emulator (its devices and its clock on the master's
    time), each answer damaged by the next of ``plan`` (then right ones)."""

    def __init__(self) -> None:
        self._bench = make_emulator(load_bench_config())
        self.plan: list[Damage] = []
        self._clock = Timekeeper(self._bench, "master")

    def reset(self, plan: list[Damage]) -> None:
        self._bench.restart()
        self._clock = Timekeeper(self._bench, "master")
        self.plan = list(plan)

    @property
    def coils(self) -> list[bool]:
        return self._bench.plant.coils()

    def answer(self, unit: int, pdu: bytes) -> bytes:
        if unit == self._clock.unit:
            return self._clock.answer(pdu, self)
        try:
            return self._bench.devices.answer(unit, pdu)
        except UnknownUnitError:
            return exception_pdu(pdu[0], GATEWAY_TARGET_FAILED)

    def damage(self) -> Damage:
        return self.plan.pop(0) if self.plan else Damage(lambda frame: frame, label="right")


class TcpPeer(Peer):
    def __init__(self) -> None:
        super().__init__()
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = self._listener.getsockname()[1]
        self._thread = threading.Thread(target=self._serve, name="fuzz-peer", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while True:
            try:
                connection, _ = self._listener.accept()
            except OSError:
                return
            with connection:
                self._answer_all(connection)

    def _answer_all(self, connection: socket.socket) -> None:
        buffer = b""
        while True:
            try:
                data = connection.recv(4096)
            except OSError:
                return
            if not data:
                return
            buffer += data
            while len(buffer) >= 8:
                tid, _, length, unit = struct.unpack_from(">HHHB", buffer)
                if len(buffer) < 6 + length:
                    break
                pdu, buffer = buffer[7:6 + length], buffer[6 + length:]
                response = self.answer(unit, pdu)
                frame = struct.pack(">HHHB", tid, 0, len(response) + 1, unit) + response
                damage = self.damage()
                sent = damage.frame(frame)
                with contextlib.suppress(OSError):
                    if sent:
                        connection.sendall(sent)
                    if damage.close:
                        connection.shutdown(socket.SHUT_RDWR)
                if damage.close:
                    return

    def close(self) -> None:
        with contextlib.suppress(OSError):  # wakes its accept(), which closing alone does not
            self._listener.shutdown(socket.SHUT_RDWR)
        self._listener.close()
        self._thread.join(timeout=2)


class RtuPeer(Peer):
    def __init__(self, port: str) -> None:
        import serial

        super().__init__()
        self._port = serial.Serial(port, 115200, timeout=0.01)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="fuzz-peer-rtu", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            try:
                data = self._port.read(256)
            except Exception:  # the port closed: done
                return
            if not data:
                buffer = b""
                continue
            buffer += data
            while (size := rtu_request_size(buffer)) is not None and len(buffer) >= size:
                frame, buffer = buffer[:size], buffer[size:]
                if crc16(frame[:-2]) != frame[-2:]:
                    buffer = b""
                    break
                reply = bytes([frame[0]]) + self.answer(frame[0], frame[1:-2])
                sent = self.damage().frame(reply + crc16(reply))
                if sent:
                    self._port.write(sent)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self._port.close()


def _drive(driver: ModbusBenchDriver, peer: Peer) -> None:
    """What a run does with its bench, each step under the rule."""
    config = load_bench_config()
    bench = SafeBench(driver, SimClock(), watchdog_polls=2, reconnect_interval_s=0.0)
    safe = config.map.relays

    def step(call: Callable[[], Any], expect: Callable[[Any], bool]) -> None:
        try:
            value = call()
        except Exception as exc:
            clear_error(exc, DriverError)
            return
        assert expect(value), f"{call} returned {value!r}"

    floats = lambda v: v is None or all(isinstance(x, float) for x in v.values())  # noqa: E731
    link = driver.link  # the emulator's time first: a session's start restarts its plant
    step(lambda: identify(link, 1, TIMEOUT_S), lambda v: v is None or isinstance(v.vendor, str))
    clock = EmulatorClock(link)
    step(lambda: clock.start(0.1), lambda v: v is None)
    step(lambda: clock.advance(10_000_000), lambda v: v is None)
    step(clock.plant_time_ns, lambda v: isinstance(v, int))
    step(clock.release, lambda v: v is None)
    step(bench.open, lambda v: v is None)
    step(bench.read_power, floats)
    step(bench.read_levels, floats)
    step(lambda: bench.set_relays({"P1": True}), lambda v: set(v) == {"P1"})
    step(bench.readback, lambda v: v is None or all(isinstance(x, bool) for x in v.values()))
    try:
        bench.safe_state()
    except Exception as exc:
        clear_error(exc, DriverError)
        return
    if not bench.watchdog.lost:
        actual = peer.coils
        wrong = {n: actual[r.coil] for n, r in safe.items() if actual[r.coil] != r.safe}
        assert not wrong, f"safe state reported done, relays {wrong} are not at their safe level"


@contextlib.contextmanager
def tcp_rig() -> Iterator[Check]:
    peer = TcpPeer()
    config = load_bench_config()

    def check(plan: list[Damage]) -> None:
        peer.reset(plan)
        link = ModbusLink(BusSpec("tcp", host="127.0.0.1", port=peer.port), TIMEOUT_S, 2)
        driver = ModbusBenchDriver(link, config.map)
        try:
            with bound("the bench driver against a damaging peer"):
                _drive(driver, peer)
        finally:
            driver.close()

    try:
        yield check
    finally:
        peer.close()


@contextlib.contextmanager
def rtu_rig() -> Iterator[Check]:
    config = load_bench_config()
    with NullModem() as modem:
        peer = RtuPeer(modem.ports[1])

        def check(plan: list[Damage]) -> None:
            peer.reset(plan)
            link = ModbusLink(BusSpec("rtu", device=modem.ports[0]), TIMEOUT_S, 2)
            driver = ModbusBenchDriver(link, config.map)
            try:
                with bound("the bench driver against a damaging peer"):
                    _drive(driver, peer)
            finally:
                driver.close()

        try:
            yield check
        finally:
            peer.close()


PLANS = st.lists(damages(), min_size=1, max_size=12)
TARGETS = (
    Target("modbus-tcp-driver", PLANS, tcp_rig, examples=20),
    Target("modbus-rtu-driver", PLANS, rtu_rig, examples=6),
)
