"""The bench plant behind pymodbus servers (Modbus TCP or RTU over a serial port).

Three devices share one server, as on the real bench's RS-485 line or TCP gateway:
unit ``units.relays`` (coils), ``units.meter`` (SDM630 input registers, float32 high word
first), ``units.levels`` (level sensors, float32). Units and register maps come in a
:class:`ServerSettings` (:mod:`hil.bench.config` reads them from the bench config).

pymodbus 3.16's datastore (``SimDevice``) cannot give the exception codes a real device gives,
so every function code is served by a small request class bound to :class:`BenchDevices`
(registered through the server's documented ``custom_pdu`` hook):

* FC05 with a value other than FF00/0000: pymodbus decodes any non-zero value as "on"; here
  it is exception 3 (illegal data value), as the Modbus specification requires;
* a quantity outside 1..max (meter: 80 registers, the SDM630's limit; other units: the
  specification's 125 registers, 2000 coils) is exception 3, checked before the address as in
  the specification's request-processing diagrams (pymodbus would raise in decode instead);
* an address outside a device's map, or a read that splits a float, is exception 2;
* a function code the unit does not have is exception 1;
* an unknown unit: no answer (RTU: nobody on the line has that address) or exception 0x0B
  (TCP: a gateway whose target did not respond), per ``emulator.unknown_unit``;
* every other function code 1..127 (pymodbus answers some itself, e.g. FC08 diagnostics, and
  answers an unknown one with function byte 0x80) is exception 1 with function byte FC|0x80;
  a request too short for its function is exception 3;
* a Modbus TCP frame with a non-zero protocol id is discarded whole (pymodbus would keep it in
  its buffer and answer nothing on that connection again); the next frame is answered.

Faults (:mod:`emulators.faults`) are played here: the Modbus kinds in :class:`FaultyHandler`
(delay, drop, exception, close, corrupt_crc), the plant kinds in :class:`BenchDevices`
(freeze, weld) and :class:`EmulatedBench` (load_step), all on the plant's clock.
"""

from __future__ import annotations

import asyncio
import logging
import math
import struct
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import NoSuchIdException
from pymodbus.framer.socket import FramerSocket
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadCoilsResponse,
    ReadDiscreteInputsRequest,
    WriteMultipleCoilsRequest,
    WriteMultipleCoilsResponse,
    WriteSingleCoilRequest,
    WriteSingleCoilResponse,
)
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadInputRegistersRequest,
    ReadInputRegistersResponse,
    ReadWriteMultipleRegistersRequest,
    WriteMultipleRegistersRequest,
    WriteSingleRegisterRequest,
)
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import SimData, SimDevice
from pymodbus.transport import CommType

from emulators.bench.plant import BenchPlant, PlantSpec, Snapshot
from emulators.faults import Fault, FaultSchedule, for_emulator
from hil.core.errors import ConfigError, HilError

SPEC_MAX_REGISTERS = 125   # Modbus spec, FC03/FC04
SPEC_MAX_COILS = 2000      # Modbus spec, FC01
SPEC_MAX_WRITE_COILS = 0x07B0  # Modbus spec, FC15
COIL_ON, COIL_OFF = 0xFF00, 0x0000

logging.getLogger("pymodbus").addHandler(logging.NullHandler())  # we report errors ourselves


UNKNOWN_UNIT_POLICIES = ("auto", "exception", "silent")
#: the function codes each device has, as its real counterpart: a relay module reads (FC01)
#: and writes (FC05, FC15) coils; the SDM630 meter and the level sensors read input registers
FUNCTIONS = {"relays": (1, 5, 15), "meter": (4,), "levels": (4,)}


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

    def check(self, address: int, count: int) -> ExcCodes | None:
        if not 1 <= count <= self.max_count:
            return ExcCodes.ILLEGAL_VALUE
        if address < self.first or address + count > self.end:
            return ExcCodes.ILLEGAL_ADDRESS
        if (address - self.first) % 2 or count % 2:  # a read must not split a float
            return ExcCodes.ILLEGAL_ADDRESS
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
        """The device at ``unit``; an unknown unit raises (pymodbus then answers per policy)."""
        for role, known in self.units.items():
            if unit == known:
                return role
        raise NoSuchIdException(f"no device at unit {unit}")

    def read_coils(self, unit: int, address: int, count: int) -> list[bool] | ExcCodes:
        if self.role(unit) != "relays":
            return ExcCodes.ILLEGAL_FUNCTION
        if not 1 <= count <= SPEC_MAX_COILS:
            return ExcCodes.ILLEGAL_VALUE
        coils = self.plant.coils()
        if address + count > len(coils):
            return ExcCodes.ILLEGAL_ADDRESS
        return coils[address:address + count]

    def write_coils(self, unit: int, address: int, values: list[bool]) -> ExcCodes | None:
        if self.role(unit) != "relays":
            return ExcCodes.ILLEGAL_FUNCTION
        if address + len(values) > self.plant.n_coils:
            return ExcCodes.ILLEGAL_ADDRESS
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

    def read_input_registers(self, unit: int, address: int, count: int) -> list[int] | ExcCodes:
        role = self.role(unit)
        if role == "relays":
            return ExcCodes.ILLEGAL_FUNCTION
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

    def unsupported(self, unit: int) -> ExcCodes:
        self.role(unit)
        return ExcCodes.ILLEGAL_FUNCTION

    def malformed(self, unit: int, function_code: int) -> ExcCodes:
        """A request too short for its function: 3, or 1 if the unit lacks the function."""
        if function_code not in FUNCTIONS[self.role(unit)]:
            return ExcCodes.ILLEGAL_FUNCTION
        return ExcCodes.ILLEGAL_VALUE


def _exception(request: ModbusPDU, code: ExcCodes) -> ExceptionResponse:
    return ExceptionResponse(request.function_code, code)


def request_classes(devices: BenchDevices) -> list[type[ModbusPDU]]:
    """Request classes for every function code 1..127, bound to ``devices``."""

    class Checked(ModbusPDU):
        """A request whose body may be too short: then exception 3, not pymodbus's 0x80."""

        malformed = False

        def decode(self, data: bytes) -> None:
            try:
                self.decode_body(data)
            except (struct.error, IndexError, ValueError):
                self.malformed = True

        def decode_body(self, data: bytes) -> None:
            super().decode(data)

        async def datastore_update(self, context: Any, device_id: int) -> ModbusPDU:
            if self.malformed:
                return _exception(self, devices.malformed(device_id, self.function_code))
            return await self.answer(device_id)

        async def answer(self, device_id: int) -> ModbusPDU:
            raise NotImplementedError

    class ReadCoils(Checked, ReadCoilsRequest):
        def decode_body(self, data: bytes) -> None:  # quantity checked in answer
            self.address, self.count = struct.unpack(">HH", data[:4])

        async def answer(self, device_id: int) -> ModbusPDU:
            bits = devices.read_coils(device_id, self.address, self.count)
            if isinstance(bits, ExcCodes):
                return _exception(self, bits)
            return ReadCoilsResponse(dev_id=device_id, transaction_id=self.transaction_id,
                                     bits=bits)

    class WriteSingleCoil(Checked, WriteSingleCoilRequest):
        raw_value = 0

        def decode_body(self, data: bytes) -> None:
            self.address, self.raw_value = struct.unpack(">HH", data[:4])
            self.bits = [self.raw_value == COIL_ON]

        async def answer(self, device_id: int) -> ModbusPDU:
            if devices.role(device_id) != "relays":
                return _exception(self, ExcCodes.ILLEGAL_FUNCTION)
            if self.raw_value not in (COIL_ON, COIL_OFF):
                return _exception(self, ExcCodes.ILLEGAL_VALUE)
            if error := devices.write_coils(device_id, self.address, list(self.bits)):
                return _exception(self, error)
            return WriteSingleCoilResponse(address=self.address, bits=list(self.bits),
                                           dev_id=device_id, transaction_id=self.transaction_id)

    class WriteMultipleCoils(Checked, WriteMultipleCoilsRequest):
        async def answer(self, device_id: int) -> ModbusPDU:
            if devices.role(device_id) != "relays":
                return _exception(self, ExcCodes.ILLEGAL_FUNCTION)
            consistent = (1 <= self.count <= SPEC_MAX_WRITE_COILS
                          and self.byte_count == (self.count + 7) // 8
                          and self.data_byte_count == self.byte_count)
            if not consistent:
                return _exception(self, ExcCodes.ILLEGAL_VALUE)
            if error := devices.write_coils(device_id, self.address, list(self.bits)):
                return _exception(self, error)
            return WriteMultipleCoilsResponse(address=self.address, count=self.count,
                                              dev_id=device_id,
                                              transaction_id=self.transaction_id)

    class ReadInputRegisters(Checked, ReadInputRegistersRequest):
        def decode_body(self, data: bytes) -> None:  # quantity checked in answer
            self.address, self.count = struct.unpack(">HH", data[:4])

        async def answer(self, device_id: int) -> ModbusPDU:
            words = devices.read_input_registers(device_id, self.address, self.count)
            if isinstance(words, ExcCodes):
                return _exception(self, words)
            return ReadInputRegistersResponse(dev_id=device_id,
                                              transaction_id=self.transaction_id,
                                              registers=words)

    served: list[type[ModbusPDU]] = [ReadCoils, WriteSingleCoil, WriteMultipleCoils,
                                     ReadInputRegisters]
    bases: dict[int, type[ModbusPDU]] = {base.function_code: base for base in (
        ReadDiscreteInputsRequest, ReadHoldingRegistersRequest, WriteSingleRegisterRequest,
        WriteMultipleRegistersRequest, ReadWriteMultipleRegistersRequest)}
    taken = {cls.function_code for cls in served}
    return [*served, *(_unsupported(devices, code, bases.get(code))
                       for code in range(1, 128) if code not in taken)]


def _unsupported(devices: BenchDevices, code: int, base: type[ModbusPDU] | None
                 ) -> type[ModbusPDU]:
    """Function ``code``, which no unit has: exception 1 (an unknown unit: no answer/0x0B).
    pymodbus's own class, where it has one, keeps its RTU frame size; any other code is taken
    as the common 8-byte RTU request."""

    def decode(self: ModbusPDU, data: bytes) -> None:
        return None

    async def datastore_update(self: ModbusPDU, context: Any, device_id: int) -> ModbusPDU:
        return _exception(self, devices.unsupported(device_id))

    namespace: dict[str, Any] = {"function_code": code, "sub_function_code": -1,
                                 "decode": decode, "datastore_update": datastore_update}
    if base is None:
        namespace["rtu_frame_size"] = 8
    return type(f"Unsupported{code}", (base or ModbusPDU,), namespace)


class DiscardingSocketFramer(FramerSocket):
    """Modbus TCP framing that drops a whole frame with a non-zero protocol id (pymodbus keeps
    it at the head of its buffer, and the connection answers nothing after it)."""

    def decode(self, data: bytes) -> tuple[int, int, int, bytes]:
        skipped = 0
        while len(data) - skipped >= self.MIN_SIZE and int.from_bytes(
                data[skipped + 2:skipped + 4], "big"):
            size = int.from_bytes(data[skipped + 4:skipped + 6], "big") + 6
            if len(data) - skipped < size:
                break
            skipped += size
        if skipped == 0:
            return super().decode(data)
        used, dev_id, tid, frame = super().decode(data[skipped:])
        return skipped + used, dev_id, tid, frame


class FaultyHandler(ServerRequestHandler):
    """One client connection; plays the Modbus faults of the schedule on every request."""

    faults: FaultSchedule

    async def handle_request(self) -> None:
        request = self.last_pdu
        if request is None:
            return
        unit = request.dev_id
        self._corrupt = False
        for fault in self._active("delay", unit):
            self.faults.hit(fault)
            await asyncio.sleep(fault.params["ms"] / 1000)
        for fault in self._active("close", unit):
            self.faults.hit(fault)
            if self.comm_params.comm_type != CommType.SERIAL:  # a serial line has no connection
                self.transport.close()
            return
        for fault in self._active("drop", unit):
            if self.faults.hit(fault) % fault.params["every"] == 0:
                return
        for fault in self._active("exception", unit):
            self.faults.hit(fault)
            response = ExceptionResponse(request.function_code, fault.params["code"])
            response.transaction_id, response.dev_id = request.transaction_id, unit
            self.server_send(response, self.last_addr)
            return
        for fault in self._active("corrupt_crc", unit):
            self.faults.hit(fault)
            self._corrupt = True
        self.last_pdu = request  # a delay may have let another request in
        await super().handle_request()

    def _active(self, kind: str, unit: int) -> list[Fault]:
        return [f for f in self.faults.active(kind) if f.params["unit"] in (0, unit)]

    def pdu_send(self, pdu: ModbusPDU, addr: tuple | None = None) -> None:
        if not getattr(self, "_corrupt", False):
            super().pdu_send(pdu, addr)
            return
        packet = bytearray(self.framer.buildFrame(pdu))
        packet[-1] ^= 0xFF  # RTU: the CRC's last byte; TCP: the last data byte
        self.low_level_send(bytes(packet), addr=addr)


def _with_faults(server_class: type[Any]) -> type[Any]:
    class Server(server_class):  # type: ignore[misc, valid-type]
        """A pymodbus server whose connections play ``faults``."""

        def __init__(self, *args: Any, faults: FaultSchedule, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.faults = faults
            framer: type[Any] = self.framer  # type: ignore[has-type]
            if framer is FramerSocket:
                self.framer = DiscardingSocketFramer

        def callback_new_connection(self) -> ServerRequestHandler:
            handler = FaultyHandler(self, self.trace_packet, self.trace_pdu,
                                    self.trace_connect)
            handler.faults = self.faults
            return handler

    Server.__name__ = f"Faulty{server_class.__name__}"
    return Server


FaultyTcpServer = _with_faults(ModbusTcpServer)
FaultySerialServer = _with_faults(ModbusSerialServer)


class ServerThread:
    """A pymodbus server with its own asyncio loop in a background thread."""

    def __init__(self, devices: BenchDevices, unknown_unit: str) -> None:
        self.devices = devices
        self.unknown_unit = unknown_unit
        self.address: tuple[str, int] | str | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None

    def _silent(self, transport: str) -> bool:
        if self.unknown_unit == "auto":
            return transport == "rtu"
        return self.unknown_unit == "silent"

    def start_tcp(self, host: str, port: int) -> tuple[str, int]:
        def make() -> ModbusTcpServer:
            return FaultyTcpServer(
                _placeholder_context(), address=(host, port), faults=self.devices.faults,
                ignore_missing_devices=self._silent("tcp"),
                custom_pdu=request_classes(self.devices),
            )

        self._start(make, f"{host}:{port}", "address in use or not available")
        assert isinstance(self.address, tuple)
        return self.address

    def start_serial(self, port: str, baudrate: int, parity: str, stopbits: int,
                     bytesize: int) -> str:
        def make() -> ModbusSerialServer:
            return FaultySerialServer(
                _placeholder_context(), port=port, baudrate=baudrate, parity=parity,
                faults=self.devices.faults,
                stopbits=stopbits, bytesize=bytesize,
                ignore_missing_devices=self._silent("rtu"),
                custom_pdu=request_classes(self.devices),
            )

        self._start(make, port, "no such serial port, or it is busy or not a tty")
        return port

    def _start(self, make: Any, where: str, failure: str) -> None:
        if self._thread is not None:
            raise HilError("emulator server already started")
        self._started.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, args=(make, failure),
                                        name="bench-modbus", daemon=True)
        self._thread.start()
        self._started.wait()
        if self._error is not None:
            self._thread.join()
            self._thread = None
            raise HilError(f"bench emulator cannot listen on {where}: {self._error}")

    def _run(self, make: Any, failure: str) -> None:
        try:
            asyncio.run(self._serve(make, failure))
        except BaseException as exc:  # reported to the starting thread
            self._error = exc
            self._started.set()

    async def _serve(self, make: Any, failure: str) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        server = make()
        try:
            await server.serve_forever(background=True)
        except RuntimeError:  # pymodbus logs the OS error and raises this
            raise OSError(failure) from None
        transport = server.transport
        sockets = getattr(transport, "sockets", None)
        if sockets:
            host, port = sockets[0].getsockname()[:2]
            self.address = (host, port)
        else:
            self.address = server.comm_params.source_address[0]
        self._started.set()
        await self._stop.wait()
        await server.shutdown()

    def stop(self) -> None:
        if self._thread is None:
            return
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(timeout=5)
        self._thread = None


def _placeholder_context() -> SimDevice:
    """pymodbus wants a datastore; every function code is answered by our classes instead."""
    return SimDevice(id=0, simdata=[SimData(0)])


class EmulatedBench:
    """Plant + Modbus server: the whole bench in-process.

    ``serve_tcp()`` (127.0.0.1, port 0 = any free port) or ``serve_serial()`` starts the server
    in a background thread. Then either :meth:`step` (lockstep: whoever owns the clock steps
    the plant, and a driver reading after a step sees exactly that step's snapshot) or
    ``run_realtime()`` (a thread steps the plant on the wall clock).
    """

    def __init__(self, plant: PlantSpec, server: ServerSettings,
                 faults: list[Fault] | tuple[Fault, ...] = (),
                 on_fault: Any = None) -> None:
        self.plant = BenchPlant(plant)
        faults = for_emulator(faults, "bench")
        relays = set(self.plant.relays)
        for fault in faults:
            if fault.kind == "weld" and fault.params["relay"] not in relays:
                raise ConfigError(f"fault {str(fault)!r}: no relay {fault.params['relay']!r} "
                                  f"(relays: {', '.join(sorted(relays))})")
        #: the faults played, on the plant's clock; ``faults.events`` records each
        self.faults = FaultSchedule(faults, lambda: self.plant.t_s, on_fault)
        self.devices = BenchDevices(self.plant, server, self.faults)
        self._server = ServerThread(self.devices, server.unknown_unit)
        self.url = ""
        self._realtime: threading.Thread | None = None
        self._stop_realtime = threading.Event()

    def serve_tcp(self, host: str = "127.0.0.1", port: int = 0) -> str:
        """Listen on TCP; return the bus URL (with the port actually bound)."""
        host, port = self._server.start_tcp(host, port)
        self.url = f"modbus-tcp://{host}:{port}"
        return self.url

    def serve_serial(self, port: str, baudrate: int = 115200, parity: str = "N",
                     stopbits: int = 1, bytesize: int = 8) -> str:
        """Serve Modbus RTU on a serial port (a real one or one end of a pty pair)."""
        self._server.start_serial(port, baudrate, parity, stopbits, bytesize)
        self.url = f"modbus-rtu://{port}?baud={baudrate}&parity={parity}"
        return self.url

    @property
    def port(self) -> int:
        address = self._server.address
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

    def run_realtime(self) -> None:
        """Step the plant in a background thread, following the monotonic clock."""
        if self._realtime is not None:
            return
        self._stop_realtime.clear()
        self._realtime = threading.Thread(target=self._follow_wall_clock, name="bench-plant",
                                          daemon=True)
        self._realtime.start()

    def _follow_wall_clock(self) -> None:
        plant, dt = self.plant, self.plant.dt
        t0, k0 = time.monotonic(), plant.k
        while not self._stop_realtime.is_set():
            target = k0 + math.floor((time.monotonic() - t0) / dt)
            while plant.k < target:
                self._step_plant()
            next_at = t0 + (plant.k - k0 + 1) * dt
            self._stop_realtime.wait(max(next_at - time.monotonic(), 0.0))

    def stop(self) -> None:
        self._stop_realtime.set()
        if self._realtime is not None:
            self._realtime.join(timeout=5)
            self._realtime = None
        self._server.stop()

    def __enter__(self) -> EmulatedBench:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()
