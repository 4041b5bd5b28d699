"""``hil emulate bench`` as a standalone process: where it listens, real time, clean stops,
one-line errors (one from a ``hil`` process, the others from the command line run in this
process: :func:`hil_here`)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pymodbus.client import ModbusSerialClient, ModbusTcpClient

from hil.emulators.null_modem import NullModem
from tests.cli import hil_here
from tests.pymodbus_bench import ANSWER_S
from tests.served_here import bench_served_here

pytestmark = [pytest.mark.timeout(60), pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]


# ``python -m hil`` as a shell starts it in the foreground, Ctrl-C not ignored: a suite run as
# a background job (``make test &``) ignores SIGINT, and its children would inherit that
AT_A_TERMINAL = ("import runpy, signal, sys; signal.signal(signal.SIGINT, "
                 "signal.default_int_handler); sys.argv[0] = 'hil'; "
                 "runpy.run_module('hil', run_name='__main__')")


def hil(*args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-c", AT_A_TERMINAL, *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def levels(client) -> list[float]:
    regs = client.read_input_registers(0, count=4, device_id=3).registers
    return client.convert_from_registers(regs, client.DATATYPE.FLOAT32)


def only_hardening(err: str) -> bool:
    """Nothing on stderr but what the emulator says of its real-time hardening (granted or
    refused, each step a line, and the warning naming what was refused)."""
    return all(line.startswith(("hil: real-time: ", "hil: warning: the bench emulator serves "
                                "without")) for line in err.splitlines())


def test_tcp_emulator_runs_in_real_time_and_stops_on_ctrl_c():
    proc = hil("emulate", "bench", "--tcp", "127.0.0.1:0")
    try:
        line = proc.stdout.readline()
        match = re.search(r"listening on modbus-tcp://127\.0\.0\.1:(\d+) \(relays unit 1, "
                          r"meter unit 2, levels unit 3\); Ctrl-C stops", line)
        assert match, line
        client = ModbusTcpClient("127.0.0.1", port=int(match.group(1)), timeout=1, retries=0)
        assert client.connect()
        assert not client.write_coil(2, True, device_id=1).isError()   # P1 refills q1
        before = time.monotonic()
        start = levels(client)[0]
        time.sleep(0.6)
        rise = levels(client)[0] - start
        elapsed = time.monotonic() - before
        # the plant follows the wall clock: the level moves, never faster than 5 per second
        # (how closely a loaded machine keeps up is not this test's business)
        assert 0 < rise <= 5.0 * elapsed + 0.05
        client.close()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=10)
    finally:
        proc.kill()
    assert proc.returncode == 0 and only_hardening(err)
    assert re.search(r"bench emulator stopped after [\d.]+ s \(plant time [\d.]+ s\)", out)


def test_serial_emulator_on_a_pty_stops_on_sigterm():
    with NullModem() as modem:
        proc = hil("emulate", "bench", "--serial", modem.ports[1], "--seed", "3")
        try:
            line = proc.stdout.readline()
            assert f"listening on modbus-rtu://{modem.ports[1]}?baud=115200&parity=N" in line
            client = ModbusSerialClient(modem.ports[0], baudrate=115200, timeout=ANSWER_S,
                                        retries=0)
            assert client.connect()
            assert levels(client) == [55.0, 65.0]
            assert client.read_coils(0, count=8, device_id=1).bits[:8] == [False] * 8
            client.close()
            proc.send_signal(signal.SIGTERM)
            out, err = proc.communicate(timeout=10)
        finally:
            proc.kill()
    assert proc.returncode == 0 and only_hardening(err) and "bench emulator stopped" in out


@pytest.mark.parametrize(("args", "config", "why", "outside"), [
    (["--tcp", "127.0.0.1:0"], '[relays.P1]\ncoil = "two"\n',
     "key 'relays.P1.coil' must be an integer", True),
    (["--tcp", "127.0.0.1:0"], "[meter.registers]\nva_l1 = 0x0001\n", "overlaps", False),
    (["--tcp", "127.0.0.1:0"], "[units]\nmeter = 1\n", "three different unit ids", False),
    (["--tcp", "127.0.0.1:0"], "[relays\n", "invalid TOML", False),
    (["--serial", "/dev/no-such-port"], "", "cannot listen on /dev/no-such-port", False),
])
def test_garbage_in_is_one_error_line(tmp_path, capfd, args, config, why, outside):
    path = tmp_path / "bad.toml"
    path.write_text(config)
    if outside:
        proc = hil("emulate", "bench", *args, "--config", str(path))
        out, err = proc.communicate(timeout=20)
        status = proc.returncode
    else:
        done = hil_here(capfd, "emulate", "bench", *args, "--config", str(path))
        status, out, err = done.returncode, done.stdout, done.stderr
    assert status == 2 and out == ""
    assert err.startswith("hil: error: ") and err.count("\n") == 1 and why in err, err


def test_busy_port_is_one_error_line(capfd):
    with bench_served_here() as first:  # the port's holder: a bench emulator in this process
        port = first.url.rsplit(":", 1)[1]
        done = hil_here(capfd, "emulate", "bench", "--tcp", f"127.0.0.1:{port}")
        status, err = done.returncode, done.stderr
    assert status == 2 and err.count("\n") == 1
    assert f"cannot listen on 127.0.0.1:{port}" in err
