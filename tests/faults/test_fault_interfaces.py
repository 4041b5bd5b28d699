"""The ways to ask for faults (``--fault``, ``--faults F.toml``, ``[faults]``, the Python API,
the ``hil_faults`` marker), their strict parsing, and the emulators' stop on SIGTERM."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil import api
from hil.bench.config import load_bench_config
from hil.cli.main import main
from hil.drivers.bench.modbus import LinkError, ModbusBenchDriver, ModbusLink, parse_bus_url
from hil.emulators.faults import FaultSchedule, parse_fault
from hil.errors import ConfigError
from tests.pymodbus_bench import ANSWER_S

REPO = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.timeout(60), pytest.mark.slow]


def test_a_fault_spec_is_parsed_with_its_defaults():
    fault = parse_fault("drop@5-8")
    assert (fault.kind, fault.start_s, fault.end_s, dict(fault.params)) == (
        "drop", 5.0, 8.0, {"every": 1, "unit": 0})
    emcy = parse_fault("emcy@1.5:code=0x4310")
    assert emcy.params == {"code": 0x4310} and math.isinf(emcy.end_s)
    assert str(parse_fault(str(emcy))) == str(emcy)  # round trip through --fault


@pytest.mark.parametrize(("spec", "message"), [
    ("drop", "expected KIND@START[-END][:KEY=VALUE,...]"),
    ("dorp@1", "unknown fault kind 'dorp'"),
    ("drop@5-3", "the window ends (3 s) before it starts (5 s)"),
    ("delay@0", "delay needs ms="),
    ("delay@0:ms=-3", "ms = -3.0 is not valid (answer this many ms late)"),
    ("drop@0:every=0", "every = 0 is not valid"),
    ("drop@0:evry=2", "drop has no parameter 'evry' (parameters: every, unit)"),
    ("exception@0:code=x", "code: 'x' is not an integer"),
    ("freeze@0:device=relays", "device = 'relays' is not valid (meter | levels)"),
    ("silent@0:ms=1", "silent has no parameter 'ms' (parameters: none)"),
])
def test_a_bad_fault_spec_is_one_line_naming_it(spec, message):
    with pytest.raises(ConfigError) as info:
        parse_fault(spec)
    text = str(info.value)
    assert message in text and "\n" not in text and text.startswith(f"--fault {spec!r}")


def test_a_fault_is_recorded_once_when_it_starts():
    now = [0.0]
    lines: list[str] = []
    schedule = FaultSchedule([parse_fault("drop@1-2")], lambda: now[0], lines.append)
    assert schedule.active("drop") == [] and schedule.events == []
    now[0] = 1.5
    assert len(schedule.active("drop")) == 1 and len(schedule.active("drop")) == 1
    now[0] = 2.0
    assert schedule.active("drop") == []
    unix_s = schedule.events[0].pop("unix_s")
    assert abs(unix_s - time.time()) < 5
    assert schedule.events == [{"t_s": 1.5, "fault": "drop@1-2:every=1,unit=0",
                                "kind": "drop"}]
    assert lines == [f"drop@1-2:every=1,unit=0 injected at t=1.500 s (unix time {unix_s:.3f})"]


def test_the_bench_config_faults_table_is_strict(tmp_path):
    path = tmp_path / "bench.toml"
    path.write_text('[faults]\nschedule = ["weld@1:relay=P1", {kind = "drop", start_s = 2}]\n')
    assert [str(f) for f in load_bench_config(str(path)).faults] == [
        "weld@1:relay=P1", "drop@2:every=1,unit=0"]
    for text, message in [
        ('[faults]\nschedul = []\n', "unknown key 'faults.schedul'"),
        ('[faults]\nschedule = ["emcy@1"]\n', "a drive emulator fault, not one the bench"),
        ('[faults]\nschedule = [{kind = "drop"}]\n', "faults.schedule[0]: needs kind and start_s"),
    ]:
        path.write_text(text)
        with pytest.raises(ConfigError, match="^" + str(path)) as info:
            load_bench_config(str(path))
        assert message in str(info.value)


def test_bad_fault_flags_are_one_line_errors(capsys, tmp_path):
    with pytest.raises(SystemExit) as info:
        main(["emulate", "bench", "--tcp", "127.0.0.1:0", "--fault", "drop@x"])
    assert info.value.code == 2
    assert "error: argument --fault: expected KIND@START" in capsys.readouterr().err
    assert main(["emulate", "drive", "--socketcand", "127.0.0.1:0",
                 "--fault", "drop@1"]) == 2
    assert capsys.readouterr().err == (
        "hil: error: --fault 'drop@1:every=1,unit=0': a bench emulator fault, not one the "
        "drive emulator plays\n")
    faults = tmp_path / "f.toml"
    faults.write_text('[fault]\nschedule = []\n')
    assert main(["emulate", "bench", "--tcp", "127.0.0.1:0", "--faults", str(faults)]) == 2
    assert capsys.readouterr().err.startswith(f"hil: error: {faults}: unknown table 'fault'")


def test_the_api_starts_an_emulator_with_faults_and_lists_what_it_injected():
    config = load_bench_config()
    with api.start_bench_emulator(faults=["drop@0.5:unit=2"]) as emulator:
        driver = ModbusBenchDriver(ModbusLink(parse_bus_url(emulator.url), 0.2, 1), config.map)
        # the levels' unit is never dropped: its answers, however late a loaded machine makes
        # them, are waited for until the fault has started on the emulator's clock
        with driver.link.patient(ANSWER_S):
            assert driver.read_levels()
            deadline = time.monotonic() + 30
            while not emulator.fault_events() and time.monotonic() < deadline:
                driver.read_levels()
                time.sleep(0.05)
        with pytest.raises(LinkError):  # the meter's unit: dropped, unanswered
            driver.read_power()
        driver.close()
        assert emulator.fault_events()[0].startswith("drop@0.5:every=1,unit=2 injected at t=")
    with pytest.raises(ConfigError, match="unknown fault kind"):
        api.start_drive_emulator(faults=["melt@1"])


@pytest.mark.hil_faults("weld@0:relay=P1")
def test_the_marker_gives_the_fixture_emulator_its_faults(hil_bench):
    assert hil_bench.emulator is not None
    assert hil_bench.driver.set_relays({"P1": True}) == {"P1": "stuck"}
    assert hil_bench.emulator.fault_events()[0].startswith("weld@0:relay=P1 injected")


@pytest.mark.parametrize("argv", [
    ["bench", "--tcp", "127.0.0.1:0"],
    ["drive", "--socketcand", "127.0.0.1:0"],
])
def test_two_sigterms_a_few_ms_apart_stop_the_emulator(argv):
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    process = subprocess.Popen([sys.executable, "-m", "hil", "emulate", *argv],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env=env)
    try:
        assert process.stdout.readline().startswith("hil: ")  # ready
        process.send_signal(signal.SIGTERM)
        time.sleep(0.002)
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=15) == 0
        assert "emulator stopped" in process.stdout.read()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


LOOP_CHILD = """
from hil.core.clock import RealtimeClock
from hil.core.loop import FunctionTask
from hil.core.session import Session

session = Session({path!r}, RealtimeClock(), 0.001, kind="test")

def announce(t):  # from the first tick: the loop's signal handlers are in place
    if not announce.done:
        announce.done = print("running", flush=True) or True

announce.done = False
session.add_task(FunctionTask("sample", 1, write=announce))
session.run(duration_s=60)
session.close()
print("closed", flush=True)
"""


@pytest.mark.realtime
def test_two_sigterms_a_few_ms_apart_stop_a_loop_cleanly(tmp_path, run_python):
    from hil.core.recording.reader import read_session

    path = tmp_path / "loop.mcap"
    child = run_python(LOOP_CHILD.format(path=str(path)))
    try:
        assert child.stdout.readline().strip() == "running"
        child.send_signal(signal.SIGTERM)
        time.sleep(0.002)
        child.send_signal(signal.SIGTERM)
        out, err = child.communicate(timeout=30)
    finally:
        child.kill()
    assert child.returncode == 0, err
    assert "closed" in out
    stop = [m for _, m in read_session(path).topic("/events") if m["kind"] == "session.stop"]
    assert stop[0]["data"]["reason"] == "signal SIGTERM"


@pytest.mark.hil_faults("delay@0:ms=400")
def test_the_fixture_driver_waits_for_a_late_emulator(hil_bench):
    """Answers 400 ms late (past the packaged 0.1 s timeout, twice) still reach the fixture's
    own driver: from hil's emulator it waits up to EMULATOR_ANSWER_S for each."""
    from hil.pytest_plugin import EMULATOR_ANSWER_S

    assert EMULATOR_ANSWER_S > 0.4 * 2
    assert hil_bench.driver.set_relays({"P1": True}) == {"P1": "switched"}
    assert set(hil_bench.driver.read_levels()) == {"q1", "q2"}
    hil_bench.driver.set_relays({"P1": False})
