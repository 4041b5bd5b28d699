"""Lockstep over a noisy Modbus RTU line, from outside: ``hil bench run --bench
modbus-rtu://PTY`` (no ``--realtime``) against ``hil emulate bench --serial PTY``, both from
the command line in a folder outside the repository, through a null-modem cable that flips
bytes both ways (``noise``, emulators/null_modem.py). A flipped byte costs a retry, not the
run; a line flipping 2 % of the bytes for a while slows the run down and it completes (or ends
by the link-loss rules, its relays read back or said); a line cut for longer than
``lockstep_timeout_s`` ends the run, and the relays it left on are driven to their safe levels
once the line is back, read back, or said to be unconfirmed. After each run an independent
master (pymodbus's serial client) reads the relays. ``hil emulate line`` is the same cable in
a process of its own."""

from __future__ import annotations

import contextlib
import json
import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial
from pymodbus.client import ModbusSerialClient

from hil.core.recording.reader import read_session
from hil.emulators.faults import parse_fault
from hil.emulators.null_modem import NullModem
from tests.cli import hil_here
from tests.pymodbus_bench import short_cycle

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

#: a run's environment: hil installed, the repository not on the path
ENV = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
#: a 2 s machining cycle, few meter quantities polled (as the README advises over RTU), a
#: request timeout of 0.1 s, the emulator declared gone after 2 s without an answer
CONFIG = ("[bus]\ntimeout_s = 0.1\nlockstep_timeout_s = 2.0\n"
          '[meter]\npoll = ["va_l1", "va_l2", "va_l3", "total_va"]\n'
          + short_cycle(2.0, dwell_s=0.5))
#: a controller that keeps P2 on: the relay a lost link leaves on
HOLD_P2 = """\
class HoldP2:
    def __init__(self, params):
        pass

    def decide(self, obs):
        return {"P2": True}
"""


class AfterBytes:
    """The cable's clock: 0 until ``n`` bytes went from the emulator to the run, then 1 plus
    the seconds since (a ``noise@1-...`` window starts mid-run, whatever the machine's pace)."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.modem: NullModem | None = None
        self.at: float | None = None

    def __call__(self) -> float:
        if self.at is None:
            if self.modem is None or self.modem.carried[1] < self.n:
                return 0.0
            self.at = time.monotonic()
        return 1.0 + time.monotonic() - self.at


def noisy_line(spec: str, after_bytes: int = 0) -> NullModem:
    clock = AfterBytes(after_bytes)
    modem = NullModem(faults=[parse_fault(spec)], now=clock)
    clock.modem = modem
    return modem


@contextlib.contextmanager
def emulator_on(modem: NullModem, folder: Path) -> Iterator[Path]:
    """``hil emulate bench --serial`` on one end of ``modem`` with :data:`CONFIG` (the config
    file's path) until the block ends."""
    config = folder / "rtu.toml"
    config.write_text(CONFIG)
    emulator = subprocess.Popen(
        [sys.executable, "-m", "hil", "emulate", "bench", "--serial", modem.ports[1],
         "--config", str(config)], cwd=folder, env=ENV, stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL, text=True)
    try:
        assert emulator.stdout is not None
        assert "listening on modbus-rtu://" in emulator.stdout.readline()
        yield config
    finally:
        emulator.terminate()
        emulator.wait(10)


def run_through(modem: NullModem, folder: Path, config: Path, *flags: str
                ) -> subprocess.CompletedProcess[str]:
    """``hil bench run`` (lockstep, ``--json``) on the run's end of ``modem``."""
    return subprocess.run(
        [sys.executable, "-m", "hil", "bench", "run", "--bench",
         f"modbus-rtu://{modem.ports[0]}", "--config", str(config), "--json",
         "--out", "run.mcap", *flags], cwd=folder, env=ENV, capture_output=True, text=True,
        timeout=240)


def relays_read_by_another_master(modem: NullModem) -> list[bool]:
    """M1 M2 P1 P2 as pymodbus's serial client reads them, on the run's end of the cable."""
    client = ModbusSerialClient(modem.ports[0], baudrate=115200, timeout=2, retries=3)
    try:
        assert client.connect()
        return list(client.read_coils(0, count=4, device_id=1).bits[:4])
    finally:
        client.close()


def events_of(folder: Path) -> list[dict]:
    return [message for _, message in read_session(str(folder / "run.mcap")).topic("/events")]


def test_one_flipped_byte_in_5000_costs_a_retry_not_the_run(tmp_path):
    """Two cycles, some 20,000 bytes each way: seed 1 flips the first byte after some 6,300
    of either way's, then one in 5000 on average."""
    with noisy_line("noise@0:rate=0.0002,seed=1") as modem, \
            emulator_on(modem, tmp_path) as config:
        run = run_through(modem, tmp_path, config, "--controller", "bc", "--cycles", "2")
    assert run.returncode == 0, run.stderr
    kpis = json.loads(run.stdout)
    assert kpis["status"] == "completed" and not kpis["disturbed"]
    assert sum(modem.flipped) >= 1 and kpis["faults"]["retries"] >= 1  # asked again
    assert kpis["faults"]["failed_polls"] == kpis["faults"]["link_losses"] == 0
    retried = [e["data"]["retries"] for e in events_of(tmp_path) if e["kind"] == "link.retried"]
    assert 0 < sum(retried) <= kpis["faults"]["retries"]  # told in time (once a second at most)
    assert read_session(str(tmp_path / "run.mcap")).metadata["session"]["clock"] == "sim"


def test_a_line_flipping_2_percent_of_bytes_both_ways_mid_run(tmp_path):
    """4 s of a line flipping 2 % of the bytes each way, from about a fifth of the run on (six
    cycles, some 11,000 bytes each from the emulator): the run completes, or ends by the
    link-loss rules with its relays read back or said; the relays are where hil says."""
    with noisy_line("noise@1-5:rate=0.02,seed=2", after_bytes=24_000) as modem, \
            emulator_on(modem, tmp_path) as config:
        run = run_through(modem, tmp_path, config, "--controller", "bc", "--cycles", "6")
        relays = relays_read_by_another_master(modem)
    assert modem.flipped[0] > 0 and modem.flipped[1] > 0
    assert run.returncode in (0, 3, 4), run.stderr
    kpis = json.loads(run.stdout)
    assert kpis["faults"]["retries"] > 0
    unsafe = [line for line in run.stderr.splitlines() if line.startswith("hil: unsafe: ")]
    if run.returncode == 0:
        assert kpis["status"] == "completed" and not unsafe
    else:
        assert kpis["stop_reason"].startswith("link lost"), kpis["stop_reason"]
        # relays not confirmed safe after it: the run is unsafe (exit 4), said on one line
        assert (run.returncode == 4) == bool(unsafe) == (kpis["status"] == "unsafe")
    if not unsafe:
        assert relays == [False] * 4  # at their safe levels, as hil says


@pytest.mark.parametrize("back", [True, False], ids=["line-back", "line-dead"])
def test_a_line_cut_mid_run_ends_it_and_the_relays_are_read_back_or_said(tmp_path, back):
    """The line cut (every byte garbled) while P2 is on, for longer than lockstep_timeout_s:
    the run ends, the emulator gone. Once the line is back, within the lost link's tries, the
    relays are driven to their safe levels and read back: nothing more is said and another
    master reads them all off. A line that stays dead: one line says the relays may still be
    on, and the event bench.safe_state_unconfirmed is in the session."""
    controller = tmp_path / "hold.py"
    controller.write_text(HOLD_P2)
    window = "1-5" if back else "1"
    with noisy_line(f"noise@{window}:rate=1", after_bytes=20_000) as modem, \
            emulator_on(modem, tmp_path) as config:
        run = run_through(modem, tmp_path, config, "--controller", f"{controller}:HoldP2",
                          "--cycles", "20")
        if back:
            relays = relays_read_by_another_master(modem)
    assert run.returncode == (3 if back else 4), run.stderr  # 4: the relays unconfirmed
    kpis = json.loads(run.stdout)
    assert kpis["status"] == ("disturbed" if back else "unsafe")
    assert kpis["stop_reason"].startswith("link lost: the bench emulator is gone (no answer "
                                          "from modbus-rtu://")
    kinds = [e["kind"] for e in events_of(tmp_path)]
    assert kinds.index("link.lost") < kinds.index("link.gave_up")
    unsafe = [line for line in run.stderr.splitlines() if line.startswith("hil: unsafe: ")]
    if back:
        assert not unsafe and "bench.safe_state_unconfirmed" not in kinds
        assert relays == [False] * 4
        assert "relays at their safe levels, read back after the run" in \
            [e["message"] for e in events_of(tmp_path) if e["kind"] == "bench.safe"]
    else:
        assert unsafe == [f"hil: unsafe: relays M1, M2, P1, P2 may still be on: the bench at "
                          f"modbus-rtu://{modem.ports[0]}?baud=115200&parity=N did not answer "
                          "after the run (5 tries, 0.5 s apart)"]
        unconfirmed = [e for e in events_of(tmp_path)
                       if e["kind"] == "bench.safe_state_unconfirmed"]
        assert [e["data"]["unknown"] for e in unconfirmed] == [["M1", "M2", "P1", "P2"]]
        assert kpis["unsafe"] == [unsafe[0].removeprefix("hil: unsafe: ")]
    assert "link_losses 1" in run.stderr


def test_hil_emulate_line_flips_the_asked_bytes_and_counts_them(tmp_path):
    """``hil emulate line``: its two ends on the first line; every byte flipped at rate 1, in
    one bit; the fault on stderr when it starts; what it carried and flipped when it stops."""
    line = subprocess.Popen(
        [sys.executable, "-m", "hil", "emulate", "line", "--fault", "noise@0:rate=1,seed=4"],
        cwd=tmp_path, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL, text=True)
    try:
        assert line.stdout is not None
        first, second = re.fullmatch(r"hil: line (\S+) <-> (\S+); Ctrl-C stops\n",
                                     line.stdout.readline()).groups()
        sent = bytes(range(64))
        with serial.Serial(first, timeout=5) as a, serial.Serial(second, timeout=5) as b:
            a.write(sent)
            got = b.read(len(sent))
        assert [bin(x ^ y).count("1") for x, y in zip(sent, got, strict=True)] == [1] * 64
    finally:
        line.terminate()
        out, err = line.communicate(timeout=10)
    assert line.returncode == 0, err
    assert out.strip().endswith(f"{first} -> {second} 64 bytes, 64 flipped; "
                                f"{second} -> {first} 0 bytes, 0 flipped")
    assert "hil: fault: noise@0:rate=1.0,seed=4 injected at t=" in err


def test_a_bad_line_fault_is_one_line(tmp_path, capsys):
    """In this process (``hil emulate line`` runs from outside just above)."""
    refused = hil_here(capsys, "emulate", "line", "--fault", "drop@0", cwd=tmp_path)
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines() == [
        "hil: error: --fault 'drop@0:every=1,unit=0': a bench emulator fault, not one the line "
        "emulator plays"]
