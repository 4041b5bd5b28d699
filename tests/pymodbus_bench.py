"""A relay bench served by pymodbus's own Modbus TCP server (its SimDevice datastore), not by
hil's emulator: coils of the relay module, float32 input registers of the meter and the level
sensors (high word first), on 127.0.0.1 in a thread of the test process.

The meter's total VA and the levels move a little with every read (a real meter's noise), so
hil's frozen-sensor check stays quiet; ``meter_override(n)`` may replace the total VA of the
n-th meter read (e.g. NaN), to play a meter serving garbage for a while.

Beside it, what the tests that run ``hil bench run`` against it share: a 4 s machining cycle
(:func:`short_config`, so a real-time run is short; its polls wait 1 s, so a loaded machine
does not make the run "disturbed"), the run as a process of its own
(:func:`start_bench_run`) and the events of a session (:func:`session_events`)."""

from __future__ import annotations

import asyncio
import os
import socket
import struct
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from hil.bench.config import BenchConfig
from hil.core.recording.reader import read_session
from hil.drivers.bench.modbus import ModbusBenchDriver, ModbusLink, parse_bus_url

ROOT = Path(__file__).resolve().parents[1]
#: how long an answer a test expects may take: a read returns as soon as it is there, and a
#: busy machine may hold the emulator's thread for a while (what is tested is the answer)
ANSWER_S = 30.0


def short_config(folder: Path, period_s: float = 4.0, dwell_s: float | None = None) -> Path:
    """A bench config written in ``folder``: a ``period_s`` machining cycle (M1 and M2 on for
    its second half; ``dwell_s``: their minimum on/off time, for a cycle shorter than the
    default's) and a patient poll (a loaded machine may answer late: not what these runs
    test)."""
    path = Path(folder) / "short.toml"
    path.write_text("[bus]\ntimeout_s = 1.0\n" + short_cycle(period_s, dwell_s))
    return path


def short_cycle(period_s: float = 2.0, dwell_s: float | None = 0.5) -> str:
    """The config tables of a ``period_s`` machining cycle (M1 and M2 on for its second half;
    ``dwell_s``: their minimum on/off time), to follow a config's own tables."""
    half = period_s / 2
    text = (f"[sequence]\nperiod_s = {period_s}\n"
            f"stages = [{{ start_s = 0.0, end_s = {half}, on = [] }},\n"
            f"          {{ start_s = {half}, end_s = {period_s}, on = [\"M1\", \"M2\"] }}]\n")
    if dwell_s is not None:
        text += "".join(f"[relays.{relay}]\ndwell_s = {dwell_s}\n" for relay in ("M1", "M2"))
    return text


def start_bench_run(url: str, out: Path | str, config: Path, *extra: str, cycles: int = 1,
                    **popen: Any) -> subprocess.Popen[str]:
    """``hil bench run --controller bc`` against ``url``, in a process of its own."""
    return subprocess.Popen(
        [sys.executable, "-m", "hil", "bench", "run", "--controller", "bc", "--bench", url,
         "--cycles", str(cycles), "--config", str(config), "--out", str(out), *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env=dict(os.environ, PYTHONPATH=str(ROOT)), **popen)


def session_events(path: Path | str) -> list[dict[str, Any]]:
    """The ``/events`` of a session file."""
    return [event for _, event in read_session(str(path)).topic("/events")]


def float_words(value: float) -> list[int]:
    """float32 big-endian, high word first, as two 16-bit registers."""
    return list(struct.unpack(">2H", struct.pack(">f", value)))


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class PymodbusBench:
    """The bench on pymodbus; ``url`` is its ``modbus-tcp://`` URL once started."""

    def __init__(self, config: BenchConfig, total_va: float = 300.0, level: float = 100.0,
                 meter_override: Callable[[int], float | None] | None = None) -> None:
        self.config = config
        self.total_va, self.level = total_va, level
        self.meter_override = meter_override
        self.meter_reads = 0
        self.port = free_port()
        self.url = f"modbus-tcp://127.0.0.1:{self.port}"
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._ready = threading.Event()
        self._server: ModbusTcpServer | None = None

    def _devices(self) -> list[SimDevice]:
        server = self.config.server
        first, end = server.meter_space
        units = server.units
        total_at = server.meter_registers["total_va"]

        async def meter(function_code, start_address, address, count, registers, set_values):
            self.meter_reads += 1
            override = self.meter_override(self.meter_reads) if self.meter_override else None
            value = override if override is not None else \
                self.total_va + 0.01 * (self.meter_reads % 100)
            registers[total_at - start_address:total_at - start_address + 2] = \
                float_words(value)

        async def levels(function_code, start_address, address, count, registers, set_values):
            for k in range(len(server.level_registers)):
                registers[2 * k:2 * k + 2] = float_words(self.level + 0.001 * self.meter_reads)

        def distinct(coils=None, inputs=None):
            """The four blocks of a device (pymodbus wants each one, unused ones minimal)."""
            def bits():
                return SimData(0, count=1, values=False, datatype=DataType.BITS)

            def words():
                return SimData(0, count=1, values=0, datatype=DataType.REGISTERS)
            return ([coils or bits()], [bits()], [words()], [inputs or words()])

        return [
            SimDevice(units["relays"], simdata=distinct(
                coils=SimData(0, count=self.config.plant.coils, values=False,
                              datatype=DataType.BITS))),
            SimDevice(units["meter"], action=meter, simdata=distinct(
                inputs=SimData(first, count=end - first, values=0,
                               datatype=DataType.REGISTERS))),
            SimDevice(units["levels"], action=levels, simdata=distinct(
                inputs=SimData(0, count=2 * len(server.level_registers), values=0,
                               datatype=DataType.REGISTERS))),
        ]

    def _serve(self) -> None:
        asyncio.set_event_loop(self._loop)

        async def start() -> None:
            self._server = ModbusTcpServer(self._devices(), address=("127.0.0.1", self.port))
            await self._server.serve_forever(background=True)

        self._loop.run_until_complete(start())
        self._ready.set()
        self._loop.run_forever()

    def __enter__(self) -> PymodbusBench:
        self._thread.start()
        assert self._ready.wait(5), "pymodbus server did not start"
        return self

    def relays(self) -> dict[str, bool]:
        """The relays as the module reads them now (through hil's Modbus driver)."""
        driver = ModbusBenchDriver(ModbusLink(parse_bus_url(self.url), ANSWER_S, 2),
                                   self.config.map)
        try:
            return driver.read_relays()
        finally:
            driver.close()

    def __exit__(self, *exc: object) -> None:
        assert self._server is not None
        asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(5)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5)
