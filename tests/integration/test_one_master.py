"""One master at a time, tried with two processes: a second run on the same bench or drive bus
refuses at once (the device lock, exit 2, one line naming the run holding it); another Modbus
master switching the bench's relays, or another CANopen master sending SYNC on the drive's
bus, stops the run within about a second with the hardware in its safe state (exit 2, one
line). The bench is pymodbus's own server; the drive is hil's emulator behind its socketcand
gateway, the foreign master a plain socketcand client."""

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hil import api
from hil.bench.config import load_bench_config
from hil.drivers.bench.modbus import ModbusBenchDriver, ModbusLink, parse_bus_url
from hil.drivers.socketcand_bus import SocketcandBus
from tests.drive_processes import patient_watchdogs
from tests.pymodbus_bench import (
    ANSWER_S,
    PymodbusBench,
    session_events,
    short_config,
    start_bench_run,
)

pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
CONFIG = load_bench_config()
ENV = dict(os.environ, PYTHONPATH=str(ROOT))


def hil(*args):
    return subprocess.Popen([sys.executable, "-m", "hil", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV)


def bench_run(bench, tmp_path, name, cycles=1):
    return start_bench_run(bench.url, tmp_path / f"{name}.mcap", short_config(tmp_path),
                           cycles=cycles)


def driver_of(url):
    return ModbusBenchDriver(ModbusLink(parse_bus_url(url), ANSWER_S, 2), CONFIG.map)


def test_a_second_run_on_the_same_bench_refuses_at_once(tmp_path):
    with PymodbusBench(CONFIG) as bench:
        # the first run lasts 40 s, far beyond the second's start on a loaded machine; it is
        # interrupted once it has gone on past the second's refusal
        first = bench_run(bench, tmp_path, "first", cycles=10)
        while bench.meter_reads < 50:
            time.sleep(0.05)
        second = bench_run(bench, tmp_path, "second")
        _, stderr = second.communicate(timeout=60)
        assert first.poll() is None, first.communicate()[1]  # refused while the first runs
        assert second.returncode == 2
        lines = stderr.strip().splitlines()
        assert len(lines) == 1 and f"bench {bench.url} is in use by another hil run (pid " \
            f"{first.pid})" in lines[0], stderr
        reads = bench.meter_reads
        while bench.meter_reads - reads <= 200 and first.poll() is None:
            time.sleep(0.05)
        assert first.poll() is None, first.communicate()[1]  # it went on undisturbed
        first.send_signal(signal.SIGINT)
        assert first.wait(timeout=30) == 130
    assert not (tmp_path / "second.mcap").exists()


def test_another_master_switching_a_relay_stops_the_run(tmp_path):
    with PymodbusBench(CONFIG) as bench:
        run = bench_run(bench, tmp_path, "shared", cycles=5)
        while bench.meter_reads < 150:
            time.sleep(0.05)
        other = driver_of(bench.url)  # another Modbus master on the same bench
        try:
            other.write_relay("P2", True)
            switched = time.monotonic()
            _, stderr = run.communicate(timeout=30)
            stopped_after = time.monotonic() - switched
        finally:
            other.close()
        assert run.returncode == 2, stderr
        lines = stderr.strip().splitlines()
        assert len(lines) == 1 and "another master is driving the bench" in lines[0], stderr
        assert stopped_after < 5
        assert not any(bench.relays().values())  # all at the safe level
    kinds = [e["kind"] for e in session_events(tmp_path / "shared.mcap")]
    assert "relay.foreign_change" in kinds and "bench.foreign_master" in kinds


@pytest.mark.realtime
def test_a_second_run_on_the_same_drive_bus_refuses_and_a_foreign_sync_stops_the_first(
        tmp_path):
    # a loaded machine may starve the real-time run: generous watchdogs keep it going until
    # the foreign master stops it (what this test is about)
    config = tmp_path / "drive.toml"
    config.write_text(patient_watchdogs(safety="enabled = false\n"))
    with api.start_drive_emulator(config, harden=True) as emulator:
        first = hil("servo", "run", "--controller", "pid", "--drive", emulator.url,
                    "--config", str(config), "--realtime", "--duration", "20",
                    "--out", str(tmp_path / "first.mcap"))
        # the session file takes its name when the loop starts: the bus is locked by then
        deadline = time.monotonic() + 30
        while not (tmp_path / "first.mcap").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        second = hil("servo", "run", "--controller", "pid", "--drive", emulator.url,
                     "--duration", "1", "--out", str(tmp_path / "second.mcap"))
        _, stderr = second.communicate(timeout=30)
        assert second.returncode == 2
        assert f"drive bus {emulator.url} is in use by another hil run (pid {first.pid})" \
            in stderr
        # a master hil does not know of: a plain client of the gateway, sending SYNC
        host, port = emulator.url.removeprefix("socketcand://").split("/")[0].split(":")
        foreign = SocketcandBus("can0", host, int(port))
        stop = threading.Event()

        def sync_producer():
            while not stop.is_set():
                foreign.send_frames([(0x080, b"")])
                time.sleep(0.01)

        producer = threading.Thread(target=sync_producer, daemon=True)
        try:
            producer.start()
            started = time.monotonic()
            _, stderr = first.communicate(timeout=30)
            stopped_after = time.monotonic() - started
        finally:
            stop.set()
            producer.join(5)
            foreign.shutdown()
    assert first.returncode == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "another master on" in lines[0] and "a SYNC (0x080)" in lines[0]
    assert stopped_after < 5
    kinds = [e["kind"] for e in session_events(tmp_path / "first.mcap")]
    assert "bus.foreign_master" in kinds
    # the foreign master does not cut this one's safe stop short: quick stop, disable voltage
    assert "drive.safe_stop" in kinds and "drive.safe_stop_failed" not in kinds
