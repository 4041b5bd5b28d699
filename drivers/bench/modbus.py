"""Relay bench driver over Modbus TCP or RTU: relays (coils), power meter and level sensors.

Moves bytes only: no dwell, no decisions (``drivers/bench/safe_bench.py`` wraps it for everyone
else).
It reads no configuration: :mod:`hil.bench.config` builds the :class:`BusSettings`,
:class:`RelaySpec` and :class:`BenchMap` it is given.
pymodbus builds every request and decodes every answer; :mod:`hil.drivers.bench.lines` finds
the answer to each request among the frames that come back (the TCP transaction id; over RTU
the CRC, unit, function and length), and passes over late and foreign frames.
:class:`ModbusLink` keeps the retry rules: each try waits ``timeout_s``, ``attempts`` tries,
every reply checked against its request.

Lockstep over the wire (:meth:`ModbusLink.hold_on`), the peer follows the master's time and may
be paused (a busy machine, a debugger): every request may then take up to a generous
wall-clock bound, and one left unanswered that long means the peer is gone: that request and
every later one fail at once (:class:`PeerGoneError`), so a run against a dead peer ends
instead of hanging. TCP loses nothing: a request waits the bound in one try. A serial line
loses and garbles frames: a request left unanswered for ``timeout_s`` is asked again (each a
retry) until the bound; a request asked twice is answered twice, and the second answer is
passed over like any late one.
"""

from __future__ import annotations

import contextlib
import logging
import struct
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ModbusPDU
from pymodbus.pdu import bit_message as bits
from pymodbus.pdu import register_message as registers
from pymodbus.pdu.mei_message import ReadDeviceInformationRequest, ReadDeviceInformationResponse

from hil.drivers.bench.lines import Line, MbapLine, ReplyMismatchError, RtuLine, TcpLine
from hil.drivers.errors import DriverError, DriverSetupError

URL_FORMS = "modbus-tcp://HOST:PORT or modbus-rtu:///dev/X?baud=115200&parity=N"
EXCEPTION_NAMES = {
    1: "illegal function", 2: "illegal data address", 3: "illegal data value",
    4: "server device failure", 5: "acknowledge", 6: "server device busy",
    10: "gateway path unavailable", 11: "gateway target device failed to respond",
}
#: worth a retry: the device failed or was busy (4, 5, 6), or a gateway answered for a device
#: that did not (10, 11). Any other exception says the request itself is wrong.
TRANSIENT_CODES = (4, 5, 6, 10, 11)

logging.getLogger("pymodbus").addHandler(logging.NullHandler())  # we report errors ourselves


class LinkError(DriverError):
    """No valid answer (timeout, connection refused or lost, garbled reply) after all tries."""


class PeerGoneError(LinkError):
    """Lockstep over the wire: the peer left a request unanswered for the whole wall-clock bound
    (or cannot be reached): it is gone (stopped, killed, or paused longer than the bound)."""


class RelayStuckError(DriverError):
    """A verified write read back the other state: the relay does not follow its coil."""

    def __init__(self, message: str, relay: str, actual: bool) -> None:
        super().__init__(message)
        self.relay, self.actual = relay, actual


class DeviceError(DriverError):
    """The device answered with a Modbus exception: the request itself is wrong."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class BusSettings:
    """``[bus]``: where the bench is, how long a request may take, when the link is lost."""

    url: str                     # modbus-tcp://HOST:PORT, modbus-rtu:///dev/X?..., emulated
    timeout_s: float             # per request
    attempts: int                # tries per request before the poll counts as failed
    reconnect_interval_s: float  # while the link is lost, try to reconnect this often
    watchdog_polls: int          # this many failed polls in a row: link lost
    give_up_s: float = 30.0      # a run stops when the link stays lost this long (0: never)
    lockstep_timeout_s: float = 10.0  # lockstep over the wire: per request; beyond it, gone


@dataclass(frozen=True)
class RelaySpec:
    """One relay: its coil on the relay module, safe level and minimum on/off time."""

    name: str
    coil: int
    safe: bool
    dwell_s: float


@dataclass(frozen=True)
class BusSpec:
    """Where the bench is: a TCP endpoint or a serial line."""

    kind: str  # "tcp" | "rtu"
    host: str = ""
    port: int = 0
    device: str = ""
    baudrate: int = 115200
    parity: str = "N"
    stopbits: int = 1
    bytesize: int = 8

    @property
    def serial_settings(self) -> dict[str, Any]:
        """The serial line's settings, as pyserial names them."""
        return {"baudrate": self.baudrate, "parity": self.parity, "stopbits": self.stopbits,
                "bytesize": self.bytesize}

    @property
    def url(self) -> str:
        if self.kind == "tcp":
            return f"modbus-tcp://{self.host}:{self.port}"
        return f"modbus-rtu://{self.device}?baud={self.baudrate}&parity={self.parity}"


def parse_bus_url(url: str) -> BusSpec:
    """``modbus-tcp://HOST:PORT`` or ``modbus-rtu:///dev/X?baud=..&parity=..&stopbits=..``."""

    def bad(why: str) -> DriverSetupError:
        return DriverSetupError(f"bus URL {url!r}: {why} (expected {URL_FORMS})")

    if not isinstance(url, str):
        raise DriverSetupError(f"bus URL must be a string like {URL_FORMS}, got {url!r}")
    parts = urlsplit(url)
    if parts.scheme == "modbus-tcp":
        if parts.path not in ("", "/") or parts.query or parts.fragment:
            raise bad("a TCP URL has no path or query")
        try:
            host, port = parts.hostname, parts.port
        except ValueError as exc:
            raise bad(f"bad port ({exc})") from None
        if not host:
            raise bad("no host")
        if port is None or port == 0:
            raise bad("no port")
        return BusSpec("tcp", host=host, port=port)
    if parts.scheme == "modbus-rtu":
        if parts.netloc or not parts.path.startswith("/") or len(parts.path) < 2:
            raise bad("an RTU URL names a device path, e.g. modbus-rtu:///dev/ttyUSB0")
        options = {"baud": "115200", "parity": "N", "stopbits": "1", "bytesize": "8"}
        for key, value in parse_qsl(parts.query, keep_blank_values=True, strict_parsing=False):
            if key not in options:
                raise bad(f"unknown option {key!r} (known: {', '.join(options)})")
            options[key] = value
        try:
            baud, stopbits, bytesize = (int(options[k]) for k in ("baud", "stopbits", "bytesize"))
        except ValueError:
            raise bad("baud, stopbits and bytesize must be integers") from None
        parity = options["parity"].upper()
        if baud <= 0 or parity not in ("N", "E", "O") or stopbits not in (1, 2) \
                or bytesize not in (7, 8):
            raise bad("baud > 0, parity N|E|O, stopbits 1|2, bytesize 7|8")
        return BusSpec("rtu", device=parts.path, baudrate=baud, parity=parity,
                       stopbits=stopbits, bytesize=bytesize)
    raise bad(f"unknown scheme {parts.scheme!r}" if parts.scheme else "not a URL")


class ModbusLink:
    """One Modbus master: a timeout per try, ``attempts`` tries, every reply checked against
    its request (:mod:`hil.drivers.bench.lines` finds it among the frames that come back).
    ``line``: the line to the peer (:class:`~hil.drivers.bench.lines.InProcessLine`, say) in
    place of the one ``spec`` names."""

    def __init__(self, spec: BusSpec, timeout_s: float, attempts: int,
                 line: Line | None = None) -> None:
        self.spec = spec
        self.timeout_s = self.request_timeout_s = timeout_s
        self.attempts = attempts
        self.connections = 0  # successful (re)connections so far
        self.requests = 0     # requests asked (however many tries each took)
        self.retries = 0      # tries that failed and were tried again (or given up)
        self.bound_s: float | None = None  # lockstep over the wire: the wall-clock bound
        self.gone: str | None = None  # lockstep: why the peer is gone; None while it is not
        self.line: Line = line or (TcpLine(spec.host, spec.port, timeout_s)
                                   if spec.kind == "tcp"
                                   else RtuLine(spec.device, spec.serial_settings, timeout_s))

    @property
    def discarded(self) -> int:
        """Frames passed over so far: answers that came late, others' answers, noise."""
        return self.line.discarded

    def hold_on(self, bound_s: float) -> None:
        """Lockstep over the wire from now on: every request may take up to ``bound_s`` of wall
        time (the peer may be paused); a request unanswered that long means the peer is gone."""
        self.bound_s = bound_s
        self._wait(bound_s)

    def let_go(self) -> None:
        """Lockstep over the wire is over: requests wait the link's own timeout again (the
        peer keeps the wall clock now; a silent one is silent, not paused), and a peer that
        was gone may be asked again."""
        self.bound_s = self.gone = None
        self._wait(self.request_timeout_s)

    @contextlib.contextmanager
    def patient(self, timeout_s: float, attempts: int = 1) -> Iterator[None]:
        """Requests inside the block wait up to ``timeout_s`` each, ``attempts`` tries."""
        before = self.timeout_s, self.attempts
        self._wait(timeout_s)
        self.attempts = attempts
        try:
            yield
        finally:
            self._wait(before[0])
            self.attempts = before[1]

    def _wait(self, timeout_s: float) -> None:
        """One try waits ``timeout_s``: in one wait over TCP; over RTU asked again every
        ``request_timeout_s`` within it (a serial line loses frames)."""
        self.timeout_s = timeout_s
        self.line.timeout_s = (timeout_s if self.spec.kind == "tcp"
                               else min(timeout_s, self.request_timeout_s))

    def connect(self) -> bool:
        if self.gone is not None:
            return False
        if self.line.connected:
            return True
        if self.line.connect():
            self.connections += 1
            return True
        return False

    def close(self) -> None:
        self.line.close()

    def execute(self, what: str, request: ModbusPDU, check: Callable[[ModbusPDU], bool]
                ) -> ModbusPDU:
        """Ask ``request`` until ``check`` accepts an answer; exceptions from the device raise."""
        if self.gone is not None:
            raise PeerGoneError(f"{what}: {self.gone}: the peer is gone")
        self.requests += 1
        reason = ""
        for _ in range(self.attempts):
            if not self.connect():
                reason = f"cannot connect to {self.spec.url}"
                continue
            asked = time.monotonic()
            reply = self._try(request, check)
            if isinstance(reply, str):
                reason = reply
                self.retries += 1
                if self.bound_s is not None and time.monotonic() - asked >= self.bound_s:
                    self.gone = (f"no answer from {self.spec.url} within {self.bound_s:g} s "
                                 "(bus.lockstep_timeout_s)")
                    raise PeerGoneError(f"{what}: {self.gone}: the peer is gone") from None
                continue
            if reply.isError():
                code = int(getattr(reply, "exception_code", 0))
                name = EXCEPTION_NAMES.get(code, "unknown exception")
                if code in TRANSIENT_CODES:
                    self.retries += 1
                    reason = f"exception {code:#04x} ({name})"
                    continue
                raise DeviceError(f"{what}: device answered exception {code:#04x} ({name})", code)
            return reply
        if self.bound_s is not None and reason.startswith("cannot connect"):
            self.gone = reason
            raise PeerGoneError(f"{what}: {self.gone}: the peer is gone")
        if isinstance(self.line, MbapLine):  # given up: no backlog of it on the peer's side
            self.line.close()
        raise LinkError(f"{what}: no valid answer from {self.spec.url} after "
                        f"{self.attempts} attempt(s): {reason}")

    def _try(self, request: ModbusPDU, check: Callable[[ModbusPDU], bool]) -> ModbusPDU | str:
        """One try of ``request``: its answer, or why there is none. A serial line asks
        again every ``request_timeout_s`` within the try (each a retry); a TCP connection
        that failed, or whose peer answered the request's transaction with something else, is
        closed (the next try reconnects). A TCP connection is kept for the next try of a
        request that timed out (the late answer is passed over by its transaction id) and
        closed when the request is given up: a peer that serves a connection's requests in
        turn would otherwise build a backlog of them, and carry out its writes long after."""
        end = time.monotonic() + self.timeout_s
        while True:
            try:
                reply = self.line.ask(request, check)
            except (ReplyMismatchError, ModbusException, OSError, ValueError) as exc:
                self.line.close()
                return _first_line(exc) or type(exc).__name__
            if reply is not None:
                return reply
            if time.monotonic() >= end:
                return f"no answer within {self.timeout_s:g} s"
            self.retries += 1  # a serial line's silence: asked again

    def read_coils(self, unit: int, address: int, count: int) -> list[bool]:
        reply = self.execute(
            f"read coils {address}..{address + count - 1} of unit {unit}",
            bits.ReadCoilsRequest(address=address, count=count, dev_id=unit),
            lambda r: len(r.bits) == 8 * ((count + 7) // 8),
        )
        return list(reply.bits[:count])

    def write_coil(self, unit: int, address: int, on: bool) -> None:
        self.execute(
            f"write coil {address} of unit {unit}",
            bits.WriteSingleCoilRequest(address=address, bits=[on], dev_id=unit),
            lambda r: r.address == address and bool(r.bits[0]) == on,
        )

    def read_floats(self, unit: int, address: int, count: int) -> list[float]:
        """``count`` registers from ``address`` (FC04) as float32, high word first."""
        reply = self.execute(
            f"read input registers {address:#06x}+{count} of unit {unit}",
            registers.ReadInputRegistersRequest(address=address, count=count, dev_id=unit),
            lambda r: len(r.registers) == count,
        )
        words = reply.registers
        return list(struct.unpack(f">{count // 2}f", struct.pack(f">{count}H", *words)))

    def read_registers(self, unit: int, address: int, count: int) -> list[int]:
        """``count`` holding registers from ``address`` (FC03)."""
        reply = self.execute(
            f"read holding registers {address}+{count} of unit {unit}",
            registers.ReadHoldingRegistersRequest(address=address, count=count, dev_id=unit),
            lambda r: len(r.registers) == count,
        )
        return list(reply.registers)

    def write_register(self, unit: int, address: int, value: int) -> None:
        """One holding register (FC06)."""
        self.execute(
            f"write register {address} of unit {unit}",
            registers.WriteSingleRegisterRequest(address=address, registers=[value],
                                                 dev_id=unit),
            lambda r: r.address == address and list(r.registers) == [value],
        )

    def exchange_registers(self, unit: int, address: int, values: list[int],
                           what: str = "", accept: Callable[[list[int]], bool] | None = None
                           ) -> list[int]:
        """Holding registers from ``address`` written, then as many read back from there, in
        one request (FC23); ``accept`` tells the answer among others by the registers read
        (a numbered request's number), ``what`` names the request in errors."""
        count = len(values)
        reply = self.execute(
            what or f"read/write registers {address}+{count} of unit {unit}",
            self._exchange_request(unit, address, values),
            lambda r: len(r.registers) == count and (accept is None or accept(list(r.registers))),
        )
        return list(reply.registers)

    def post_exchange(self, unit: int, address: int, values: list[int]) -> bool:
        """:meth:`exchange_registers` sent without waiting for its answer, so the request
        after it goes in the same breath (Modbus TCP only: a server answers a connection's
        requests in order, and this answer, of another transaction, is passed over when the
        next one is read). False when it was not sent (RTU, no connection): ask it with
        :meth:`exchange_registers`. Its answer is never checked: follow it with an asked one
        now and then."""
        line = self.line
        if not isinstance(line, MbapLine) or self.gone is not None or not self.connect():
            return False
        try:
            line.post(self._exchange_request(unit, address, values))
        except (ModbusException, OSError, ValueError):
            line.close()
            return False
        return True

    @staticmethod
    def _exchange_request(unit: int, address: int, values: list[int]) -> ModbusPDU:
        return registers.ReadWriteMultipleRegistersRequest(
            read_address=address, read_count=len(values), write_address=address,
            write_registers=values, dev_id=unit)

    def read_identification(self, unit: int) -> dict[int, bytes]:
        """The basic device identification objects of ``unit`` (FC43/MEI 14, read code 1):
        ``{object id: value}`` (0 VendorName, 1 ProductCode, 2 MajorMinorRevision)."""
        reply = self.execute(
            f"read device identification of unit {unit}",
            ReadDeviceInformationRequest(read_code=1, dev_id=unit),
            lambda r: isinstance(r, ReadDeviceInformationResponse),
        )
        assert isinstance(reply, ReadDeviceInformationResponse)
        return {int(k): v if isinstance(v, bytes) else b"".join(v)
                for k, v in reply.information.items()}


def _first_line(exc: BaseException) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else ""


def plan_reads(addresses: Mapping[str, int], max_count: int, max_gap: int
               ) -> list[tuple[int, int, list[tuple[str, int]]]]:
    """Group float32 registers into requests: ``(first, count, [(name, float index)])``.

    Neighbours join one request while it stays within ``max_count`` registers and skips at
    most ``max_gap`` registers between two wanted floats.
    """
    reads: list[tuple[int, int, list[tuple[str, int]]]] = []
    for name, address in sorted(addresses.items(), key=lambda item: item[1]):
        if reads:
            first, count, names = reads[-1]
            gap = address - (first + count)
            if 0 <= gap <= max_gap and address + 2 - first <= max_count and gap % 2 == 0:
                names.append((name, (address - first) // 2))
                reads[-1] = (first, address + 2 - first, names)
                continue
        reads.append((address, 2, [(name, 0)]))
    return reads


@dataclass(frozen=True)
class BenchMap:
    """Unit ids (by role: relays, meter, levels), relays and the planned register reads
    (:func:`plan_reads`) of the meter and the level sensors."""

    units: dict[str, int]
    relays: dict[str, RelaySpec]
    meter_reads: list[tuple[int, int, list[tuple[str, int]]]]
    level_reads: list[tuple[int, int, list[tuple[str, int]]]]

    @property
    def meter_quantities(self) -> list[str]:
        return [name for _, _, names in self.meter_reads for name, _ in names]

    @property
    def level_names(self) -> list[str]:
        return [name for _, _, names in self.level_reads for name, _ in names]


class ModbusBenchDriver:
    """The bench's devices over one :class:`ModbusLink`. No dwell, no safety: see safety.py."""

    def __init__(self, link: ModbusLink, bench_map: BenchMap) -> None:
        self.link = link
        self.map = bench_map
        coils = [r.coil for r in bench_map.relays.values()]
        self._coil_first, self._coil_count = min(coils), max(coils) - min(coils) + 1

    def _read_block(self, unit: int, reads: list[tuple[int, int, list[tuple[str, int]]]]
                    ) -> dict[str, float]:
        out: dict[str, float] = {}
        for first, count, names in reads:
            floats = self.link.read_floats(unit, first, count)
            for name, index in names:
                out[name] = floats[index]
        return out

    def read_power(self) -> dict[str, float]:
        """Every polled meter quantity (``meter.poll``) of one moment."""
        return self._read_block(self.map.units["meter"], self.map.meter_reads)

    def read_levels(self) -> dict[str, float]:
        return self._read_block(self.map.units["levels"], self.map.level_reads)

    def read_relays(self) -> dict[str, bool]:
        bits = self.link.read_coils(self.map.units["relays"], self._coil_first,
                                    self._coil_count)
        return {name: bits[r.coil - self._coil_first] for name, r in self.map.relays.items()}

    def write_relay(self, name: str, on: bool) -> dict[str, bool]:
        """Switch one relay, read every relay back; raise RelayStuckError when it disagrees."""
        self.link.write_coil(self.map.units["relays"], self.map.relays[name].coil, on)
        return self.verify_relay(name, on)

    def verify_relay(self, name: str, on: bool) -> dict[str, bool]:
        """Every relay read back after a write of ``name``; RelayStuckError when it is not
        ``on``."""
        states = self.read_relays()
        if states[name] != on:
            raise RelayStuckError(f"relay {name}: wrote {'on' if on else 'off'}, read back "
                                  f"{'on' if states[name] else 'off'} (does not follow its "
                                  "coil: welded or stuck?)", name, states[name])
        return states

    def probe(self) -> None:
        """One request to every unit; the first failure raises an error naming the unit."""
        checks = (("relays", self.read_relays), ("meter", self.read_power),
                  ("levels", self.read_levels))
        for role, read in checks:
            where = f"bench {role} (unit {self.map.units[role]})"
            try:
                read()
            except DeviceError as exc:
                raise DeviceError(f"{where}: {exc}", exc.code) from None
            except LinkError as exc:
                raise LinkError(f"{where}: {exc} (is the bench there, is the unit id right?)"
                                ) from None

    def close(self) -> None:
        self.link.close()
