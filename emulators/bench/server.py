"""The bench plant behind a Modbus server (TCP or RTU over a serial port).

Three devices share one server, as on the real bench's RS-485 line or TCP gateway:
unit ``units.relays`` (coils), ``units.meter`` (SDM630 input registers, float32 high word
first), ``units.levels`` (level sensors, float32). Units and register maps come in a
:class:`ServerSettings` (:mod:`hil.bench.config` reads them from the bench config).

:meth:`BenchDevices.answer` gives each request the answer a real device gives, and the
server of :mod:`hil.emulators.bench.modbus_server` carries it over the wire:

* FC05 with a value other than FF00/0000 is exception 3 (illegal data value), as the Modbus
  specification requires;
* a quantity outside 1..max (meter: 80 registers, the SDM630's limit; other units: the
  specification's 125 registers, 2000 coils) is exception 3, checked before the address as in
  the specification's request-processing diagrams;
* an address outside a device's map, or a read that splits a float, is exception 2;
* a function code the unit does not have is exception 1 (function byte FC|0x80);
* a request too short for its function is exception 3 (1 if the unit lacks the function);
* an unknown unit: no answer (RTU: nobody on the line has that address) or exception 0x0B
  (TCP: a gateway whose target did not respond), per ``emulator.unknown_unit``;
* a Modbus TCP frame with a non-zero protocol id is discarded whole; the next is answered;
* every device answers Read Device Identification (FC 0x2B / MEI 0x0E) as hil's emulator
  (:mod:`hil.protocols.bench_clock`), so a master can tell it from a real bench.

With :meth:`EmulatedBench.follow`, its time follows the wall clock or a lockstep master
(:mod:`hil.emulators.bench.timekeeper`, which also answers the clock's unit).

Faults (:mod:`hil.emulators.faults`) are played by the server (delay, drop, exception, close,
corrupt_crc), by :class:`BenchDevices` (freeze, weld) and :class:`EmulatedBench`
(load_step), all on the plant's clock.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil.emulators.bench.modbus_server import (
    IDENTIFICATION,
    ILLEGAL_ADDRESS,
    ILLEGAL_FUNCTION,
    ILLEGAL_VALUE,
    ModbusServer,
    UnknownUnitError,
    exception_pdu,
)
from hil.emulators.bench.plant import BenchPlant, PlantSpec, Snapshot
from hil.emulators.bench.timekeeper import Timekeeper
from hil.emulators.errors import EmulatorError, EmulatorSetupError
from hil.emulators.faults import Fault, FaultSchedule, for_emulator
from hil.protocols.bench_clock import PRODUCT_CODE, PRODUCT_NAME, REVISION, VENDOR

SPEC_MAX_REGISTERS = 125   # Modbus spec, FC03/FC04
SPEC_MAX_COILS = 2000      # Modbus spec, FC01
SPEC_MAX_WRITE_COILS = 0x07B0  # Modbus spec, FC15
COIL_ON, COIL_OFF = 0xFF00, 0x0000

UNKNOWN_UNIT_POLICIES = ("auto", "exception", "silent")
#: the function codes each device has, as its real counterpart: a relay module reads (FC01)
#: and writes (FC05, FC15) coils; the SDM630 meter and the level sensors read input registers;
#: each identifies itself (FC43)
FUNCTIONS = {"relays": (1, 5, 15, 43), "meter": (4, 43), "levels": (4, 43)}
READ_DEVICE_ID = 0x0E  # its MEI type "read device identification"
#: the models the devices name (identification object 5, ModelName)
MODELS = {"relays": "relay module", "meter": "power meter (SDM630 layout)",
          "levels": "level sensors"}


@dataclass(frozen=True)
class ServerSettings:
    """What the Modbus server serves (``[units]``, the register maps and ``[emulator]`` of the
    bench config, read by :mod:`hil.bench.config`)."""

    units: dict[str, int]            # role (relays, meter, levels) -> unit id
    meter_registers: dict[str, int]  # quantity -> first register (float32)
    meter_space: tuple[int, int]     # the meter's served FC04 block [first, end)
    max_meter_registers: int         # the meter's limit per request (SDM630: 80)
    level_registers: dict[str, int]  # resource -> first register (float32)
    unknown_unit: str                # one of UNKNOWN_UNIT_POLICIES


class FloatBlock:
    """A block of input registers holding float32 values (high word first) from a snapshot."""

    def __init__(self, addresses: Mapping[str, int], first: int, end: int, max_count: int
                 ) -> None:
        self.first, self.end, self.max_count = first, end, max_count
        self._slots = {name: (address - first) // 2 for name, address in addresses.items()}
        self._cache: tuple[Any, list[int]] = (None, [])

    def words(self, values: Mapping[str, float], key: object) -> list[int]:
        """All registers of the block for ``values``; recomputed only when ``key`` changes."""
        if self._cache[0] is not key:
            floats = np.zeros((self.end - self.first) // 2, dtype=">f4")
            for name, slot in self._slots.items():
                floats[slot] = values[name]
            self._cache = (key, floats.view(">u2").tolist())
        return self._cache[1]

    def check(self, address: int, count: int) -> int | None:
        if not 1 <= count <= self.max_count:
            return ILLEGAL_VALUE
        if address < self.first or address + count > self.end:
            return ILLEGAL_ADDRESS
        if (address - self.first) % 2 or count % 2:  # a read must not split a float
            return ILLEGAL_ADDRESS
        return None


class BenchDevices:
    """What each unit answers: the plant's coils and its latest :class:`Snapshot` (or the one
    a ``freeze`` fault holds; a ``weld`` fault keeps a coil where it is)."""

    def __init__(self, plant: BenchPlant, settings: ServerSettings,
                 faults: FaultSchedule | None = None) -> None:
        self.plant = plant
        self.faults = faults or FaultSchedule([], lambda: plant.t_s)
        self._frozen: dict[str, Snapshot] = {}
        self.units = dict(settings.units)
        first, end = settings.meter_space
        self.meter = FloatBlock(settings.meter_registers, first, end,
                                settings.max_meter_registers)
        levels = settings.level_registers
        self.levels = FloatBlock(levels, min(levels.values()), max(levels.values()) + 2,
                                 SPEC_MAX_REGISTERS)

    def role(self, unit: int) -> str:
        """The device at ``unit``; an unknown unit raises (the server answers per policy)."""
        for role, known in self.units.items():
            if unit == known:
                return role
        raise UnknownUnitError(f"no device at unit {unit}")

    def read_coils(self, unit: int, address: int, count: int) -> list[bool] | int:
        if self.role(unit) != "relays":
            return ILLEGAL_FUNCTION
        if not 1 <= count <= SPEC_MAX_COILS:
            return ILLEGAL_VALUE
        coils = self.plant.coils()
        if address + count > len(coils):
            return ILLEGAL_ADDRESS
        return coils[address:address + count]

    def write_coils(self, unit: int, address: int, values: list[bool]) -> int | None:
        if self.role(unit) != "relays":
            return ILLEGAL_FUNCTION
        if address + len(values) > self.plant.n_coils:
            return ILLEGAL_ADDRESS
        welds = self.faults.active("weld")
        if welds:
            welded = {self.plant.relays[f.params["relay"]] for f in welds}
            coils = self.plant.coils()
            values = [coils[address + i] if address + i in welded else v
                      for i, v in enumerate(values)]
            for fault in welds:
                self.faults.hit(fault)
        self.plant.set_coils(address, values)
        return None

    def read_input_registers(self, unit: int, address: int, count: int) -> list[int] | int:
        role = self.role(unit)
        if role == "relays":
            return ILLEGAL_FUNCTION
        block = self.meter if role == "meter" else self.levels
        if error := block.check(address, count):
            return error
        snapshot: Snapshot = self._snapshot(role)  # one reference: one consistent step
        values = snapshot.meter if role == "meter" else snapshot.levels
        words = block.words(values, snapshot)
        start = address - block.first
        return words[start:start + count]

    def _snapshot(self, role: str) -> Snapshot:
        freezes = [f for f in self.faults.active("freeze") if f.params["device"] == role]
        if not freezes:
            self._frozen.pop(role, None)
            return self.plant.snapshot
        self.faults.hit(freezes[0])
        return self._frozen.setdefault(role, self.plant.snapshot)

    def identification(self, unit: int, body: bytes) -> bytes:
        """FC43 / MEI 0x0E: VendorName, ProductCode, MajorMinorRevision (basic) and
        ProductName, ModelName (regular), streamed (read codes 1-3) or one (code 4)."""
        role = self.role(unit)
        if len(body) < 3:
            return exception_pdu(IDENTIFICATION, ILLEGAL_VALUE)
        mei, code, first = body[0], body[1], body[2]
        if mei != READ_DEVICE_ID:
            return exception_pdu(IDENTIFICATION, ILLEGAL_FUNCTION)
        if not 1 <= code <= 4:
            return exception_pdu(IDENTIFICATION, ILLEGAL_VALUE)
        objects = {0: VENDOR, 1: PRODUCT_CODE, 2: REVISION, 4: PRODUCT_NAME, 5: MODELS[role]}
        if code == 4:
            if first not in objects:
                return exception_pdu(IDENTIFICATION, ILLEGAL_ADDRESS)
            chosen = [first]
        else:
            last = 2 if code == 1 else 0x7F
            ids = [i for i in sorted(objects) if i <= last]
            chosen = [i for i in ids if i >= first] if first in ids else ids
        values = {i: objects[i].encode() for i in chosen}
        data = b"".join(bytes([i, len(value)]) + value for i, value in values.items())
        # conformity 0x82: regular identification, stream and individual access
        return bytes([IDENTIFICATION, READ_DEVICE_ID, code, 0x82, 0, 0, len(chosen)]) + data

    def unsupported(self, unit: int) -> int:
        self.role(unit)
        return ILLEGAL_FUNCTION

    def malformed(self, unit: int, function_code: int) -> int:
        """A request too short for its function: 3, or 1 if the unit lacks the function."""
        if function_code not in FUNCTIONS[self.role(unit)]:
            return ILLEGAL_FUNCTION
        return ILLEGAL_VALUE

    def answer(self, unit: int, pdu: bytes) -> bytes:
        """The response PDU to a request PDU for ``unit`` (an exception response where a real
        device gives one); an unknown unit raises :class:`UnknownUnitError`."""
        code, body = pdu[0], pdu[1:]
        if code == IDENTIFICATION:
            return self.identification(unit, body)
        if code not in (1, 4, 5, 15):
            return exception_pdu(code, self.unsupported(unit))
        if len(body) < (5 if code == 15 else 4):
            return exception_pdu(code, self.malformed(unit, code))
        address, value = struct.unpack_from(">HH", body)
        if code == 1:
            bits = self.read_coils(unit, address, value)
            if isinstance(bits, int):
                return exception_pdu(code, bits)
            packed = bytes(sum(1 << i for i, on in enumerate(bits[k:k + 8]) if on)
                           for k in range(0, len(bits), 8))
            return bytes([code, len(packed)]) + packed
        if code == 4:
            words = self.read_input_registers(unit, address, value)
            if isinstance(words, int):
                return exception_pdu(code, words)
            return bytes([code, 2 * len(words)]) + struct.pack(f">{len(words)}H", *words)
        if self.role(unit) != "relays":
            return exception_pdu(code, ILLEGAL_FUNCTION)
        if code == 5:
            if value not in (COIL_ON, COIL_OFF):
                return exception_pdu(code, ILLEGAL_VALUE)
            error = self.write_coils(unit, address, [value == COIL_ON])
            return exception_pdu(code, error) if error else pdu[:5]
        byte_count, values = body[4], body[5:]
        if not (1 <= value <= SPEC_MAX_WRITE_COILS and byte_count == (value + 7) // 8
                and len(values) == byte_count):
            return exception_pdu(code, ILLEGAL_VALUE)
        bits = [bool(values[i // 8] >> (i % 8) & 1) for i in range(value)]
        error = self.write_coils(unit, address, bits)
        return exception_pdu(code, error) if error else pdu[:5]


class EmulatedBench:
    """Plant + Modbus server: the whole bench in-process.

    ``serve_tcp()`` (127.0.0.1, port 0 = any free port) or ``serve_serial()`` starts the server
    in a background thread. Then either :meth:`step` (lockstep in this process: whoever owns
    the clock steps the plant, and a driver reading after a step sees exactly that step's
    snapshot), :meth:`follow` (a thread steps the plant on the wall clock, and a lockstep
    master on the wire may take its time) or ``run_realtime()`` (the wall clock only).
    """

    def __init__(self, plant: PlantSpec, server: ServerSettings,
                 faults: list[Fault] | tuple[Fault, ...] = (),
                 on_fault: Any = None) -> None:
        self._spec, self._settings, self._on_fault = plant, server, on_fault
        self.plant = BenchPlant(plant)
        self._faults = for_emulator(faults, "bench")
        relays = set(self.plant.relays)
        for fault in self._faults:
            if fault.kind == "weld" and fault.params["relay"] not in relays:
                raise EmulatorSetupError(
                    f"fault {str(fault)!r}: no relay {fault.params['relay']!r} "
             f"(relays: {', '.join(sorted(relays))})")
        #: the faults played, on the plant's clock; ``faults.events`` records each
        self.faults = FaultSchedule(self._faults, lambda: self.plant.t_s, on_fault)
        self.devices = BenchDevices(self.plant, server, self.faults)
        self._unknown_unit = server.unknown_unit
        self._server: ModbusServer | None = None
        self.url = ""
        self.timekeeper: Timekeeper | None = None

    def serve_tcp(self, host: str = "127.0.0.1", port: int = 0) -> str:
        """Listen on TCP; return the bus URL (with the port actually bound)."""
        server = self._new_server("tcp")
        try:
            host, port = server.start_tcp(host, port)
        except OSError as exc:
            raise EmulatorError(f"bench emulator cannot listen on {host}:{port}: address in use or "
                           f"not available ({exc.strerror or exc})") from None
        self._server = server
        self.url = f"modbus-tcp://{host}:{port}"
        return self.url

    def serve_serial(self, port: str, baudrate: int = 115200, parity: str = "N",
                     stopbits: int = 1, bytesize: int = 8) -> str:
        """Serve Modbus RTU on a serial port (a real one or one end of a pty pair)."""
        server = self._new_server("rtu")
        try:
            server.start_serial(port, baudrate, parity, stopbits, bytesize)
        except Exception as exc:  # pyserial's SerialException, ValueError for bad settings
            raise EmulatorError(f"bench emulator cannot listen on {port}: no such serial port, or "
                           f"it is busy or not a tty ({exc})") from None
        self._server = server
        self.url = f"modbus-rtu://{port}?baud={baudrate}&parity={parity}"
        return self.url

    def _new_server(self, transport: str) -> ModbusServer:
        if self._server is not None:
            raise EmulatorError("emulator server already started")
        silent = self._unknown_unit == "silent" or (self._unknown_unit == "auto"
                                                    and transport == "rtu")
        server = ModbusServer(self._answer, self.faults, silent_unknown=silent)
        server.clock = self.timekeeper
        return server

    def _answer(self, unit: int, pdu: bytes) -> bytes:
        return self.devices.answer(unit, pdu)  # the devices of the plant now (see restart)

    def restart(self) -> None:
        """The plant and its fault schedule as they were built (a lockstep session's start):
        t = 0, initial levels, every coil off, the noise from its seed's start."""
        self.plant = BenchPlant(self._spec)
        self.faults = FaultSchedule(self._faults, lambda: self.plant.t_s, self._on_fault)
        self.devices = BenchDevices(self.plant, self._settings, self.faults)
        if self._server is not None:
            self._server.faults = self.faults

    def hold_in_process(self, request_timeout_s: float) -> None:
        """Lockstep in this process: the plant steps only by :meth:`step`, and the server answers
        as to a master holding its time whose requests wait ``request_timeout_s``: where it
        would leave the master waiting (a drop, a longer delay, an unknown unit), exception 0x0B
        at once. A busy machine then changes no answer: the session is the same, bit for bit."""
        self._serving().loop_timeout_s = request_timeout_s

    def connect_in_process(self) -> Callable[[bytes], tuple[bytes, bool]]:
        """A Modbus TCP connection to the server from a master in this process, answered in
        the master's thread (:meth:`ModbusServer.connect_in_process`)."""
        return self._serving().connect_in_process()

    def _serving(self) -> ModbusServer:
        """The server started by :meth:`serve_tcp` (or :meth:`serve_serial`)."""
        if self._server is None:
            raise EmulatorError("the emulator serves no link yet: serve_tcp() first")
        return self._server

    @property
    def port(self) -> int:
        address = self._server.address if self._server is not None else None
        return address[1] if isinstance(address, tuple) else 0

    def step(self, steps: int = 1) -> Snapshot:
        """Lockstep: advance the plant; a read after this returns this snapshot."""
        for _ in range(steps):
            self._step_plant()
        return self.plant.snapshot

    def _step_plant(self) -> None:
        if self.faults:
            steps = self.faults.active("load_step")
            self.plant.extra_va = sum(f.params["va"] for f in steps)
        self.plant.step()

    def follow(self, clock: str, on_change: Callable[[str], None] | None = None
               ) -> Timekeeper:
        """Step the plant from a background thread: on the wall clock, or on a lockstep
        master's time when one on the wire takes it (``clock``: one of
        :data:`~hil.protocols.bench_clock.CLOCKS`, as ``hil emulate bench --clock``;
        ``on_change`` hears a line each time a master takes the time or lets go)."""
        if self.timekeeper is None:
            self.timekeeper = Timekeeper(self, clock, on_change)
            if self._server is not None:
                self._server.clock = self.timekeeper
            self.timekeeper.start()
        return self.timekeeper

    def run_realtime(self) -> None:
        """Step the plant in a background thread, following the monotonic clock."""
        self.follow("wall")

    def stop(self) -> None:
        if self.timekeeper is not None:
            self.timekeeper.stop()
            self.timekeeper = None
        if self._server is not None:
            self._server.stop()
            self._server = None

    def __enter__(self) -> EmulatedBench:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()
