"""Emulators in their own processes on loopback, started and stopped from Python."""

import socket

import pytest

from hil.emulator_process import start_bench_emulator, start_drive_emulator
from hil.errors import HilError

pytestmark = [pytest.mark.slow]


def test_bench_and_drive_emulators_listen_on_loopback_and_stop():
    with start_bench_emulator(seed=3) as bench, start_drive_emulator() as drive:
        assert bench.url.startswith("modbus-tcp://127.0.0.1:")
        assert drive.url.startswith("socketcand://127.0.0.1:")
        for url in (bench.url, drive.url):
            host, port = url.split("://")[1].rsplit(":", 1)
            with socket.create_connection((host, int(port)), timeout=5):
                pass  # accepting connections
        processes = (bench.process, drive.process)
    assert all(p.returncode == 0 for p in processes)  # SIGTERM ends them cleanly


def test_an_emulator_that_cannot_start_says_why(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[plant]\nsed = 1\n")  # a misspelt seed
    with pytest.raises(HilError, match=r"the bench emulator did not start: .*plant\.sed"):
        start_bench_emulator(bad, timeout_s=30)
