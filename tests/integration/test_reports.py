"""A report for every outcome: ``hil servo run`` and ``hil bench run``, from a folder outside
the repository, print ``--json`` and write ``--junit`` when a limit, a safety stop, a fault,
Ctrl-C or a bad controller ends the run, with the exit status and the one error line as
documented (README "Limits and a verdict"). Each kind of report is read once from a ``hil``
process; more cases of the same command run the command line in this process
(:func:`hil_here`), from the same folder."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from hil import api
from hil.core.recording.reader import read_session
from tests.cli import hil_here

pytestmark = [pytest.mark.timeout(180), pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
# ``python -m hil`` as a shell starts it in the foreground, Ctrl-C not ignored (a suite run as
# a background job ignores SIGINT, and its children would inherit that)
AT_A_TERMINAL = ("import runpy, signal, sys; signal.signal(signal.SIGINT, "
                 "signal.default_int_handler); sys.argv[0] = 'hil'; "
                 "runpy.run_module('hil', run_name='__main__')")

RUNAWAY = '''
class Runaway:
    """Pushes a constant current whatever the axis does."""

    def __init__(self, reference, params):
        self.current = float(params.get("current_mA", 800.0))

    def step(self, position_deg, t_s):
        return self.current
'''


def hil(folder: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=folder, env=ENV,
                          capture_output=True, text=True, timeout=timeout)


def report(folder: Path, done: subprocess.CompletedProcess, junit: str = "report.xml"
           ) -> tuple[dict, ET.Element, dict[str, str]]:
    """The run's --json document, its JUnit suite and the suite's properties."""
    kpis = json.loads(done.stdout)
    root = ET.parse(folder / junit).getroot()
    assert root.tag == "testsuites"
    suite = root.find("testsuite")
    assert suite is not None
    properties = {p.get("name"): p.get("value") for p in suite.findall("properties/property")}
    return kpis, suite, properties


def run_case(suite: ET.Element) -> ET.Element:
    cases = [case for case in suite.findall("testcase") if case.get("name") == "run"]
    assert len(cases) == 1
    return cases[0]


def one_error_line(done: subprocess.CompletedProcess, start: str) -> str:
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(start), done.stderr
    return lines[0]


def assert_error_case(suite: ET.Element, error_type: str, line: str) -> ET.Element:
    """The suite counts one error, the test case ``run``, whose message is the error line."""
    assert suite.get("errors") == "1"
    error = run_case(suite).find("error")
    assert error is not None and error.get("type") == error_type
    assert line.endswith(error.get("message", "")) and error.text == error.get("message")
    return error


def test_a_per_tick_limit_that_stops_a_servo_run_is_a_failure_case(tmp_path):
    done = hil(tmp_path, "servo", "run", "--controller", "pid", "--duration", "0.5",
               "--limit", "abs_error_deg<=0.001", "--out", "s.mcap", "--json",
               "--junit", "report.xml")
    assert done.returncode == 1
    kpis, suite, properties = report(tmp_path, done)
    assert kpis["status"] == "violated" and kpis["passed"] is False
    assert kpis["stop_reason"] == "limit abs_error_deg<=0.001" and kpis["ticks"] < 1000
    assert (suite.get("tests"), suite.get("failures"), suite.get("errors")) == ("2", "1", "0")
    failure = suite.find("testcase/failure")
    assert failure is not None and failure.get("message", "").startswith(
        "abs_error_deg<=0.001: measured")
    run = run_case(suite)
    assert run.find("error") is None and run.find("failure") is None
    assert properties["status"] == "violated" and properties["mcap"] == "s.mcap"
    assert properties["ticks"] == str(kpis["ticks"])
    assert float(properties["step_us.p99"]) == kpis["step_us"]["p99"]


def test_a_safety_stop_of_a_servo_run_is_reported(tmp_path, capfd, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "runaway.py").write_text(RUNAWAY)
    (tmp_path / "tight.toml").write_text(
        "[safety]\nfollowing_error_deg = 5.0\nfollowing_error_ms = 5.0\n")
    done = hil_here(capfd, "servo", "run", "--controller", "runaway.py:Runaway", "--config",
                    "tight.toml", "--duration", "2", "--out", "s.mcap", "--json", "--junit",
                    "report.xml")
    assert done.returncode == 2
    line = one_error_line(done, "hil: error: safety stop at t=")
    kpis, suite, properties = report(tmp_path, done)
    assert kpis["status"] == "stopped" and kpis["stop_reason"].startswith("safety stop")
    assert kpis["error"] in line and kpis["max_error_deg"] > 5 and kpis["ticks"] < 4000
    assert_error_case(suite, "SafetyStopError", line)
    assert properties["status"] == "stopped" and properties["mcap"] == "s.mcap"
    assert float(properties["max_error_deg"]) == kpis["max_error_deg"]
    # the session holds the same KPIs
    recorded = json.loads(read_session(tmp_path / "s.mcap").metadata["kpis"]["json"])
    assert recorded["status"] == "stopped" and recorded["ticks"] == kpis["ticks"]


def test_a_drive_fault_during_a_servo_run_is_reported(tmp_path, capfd):
    # an emulator on SYNC time from power-on counts the run's time: the fault comes 0.5 s into
    # the run (long after it enabled the drive), however late the run starts
    with api.start_drive_emulator(faults=["emcy@0.5:code=0x2310"], clock="sync") as emulator:
        done = hil_here(capfd, "servo", "run", "--controller", "pid", "--drive", emulator.url,
                        "--duration", "2", "--out", "s.mcap", "--json", "--junit",
                        "report.xml", cwd=tmp_path)
    assert done.returncode == 2
    line = one_error_line(done, "hil: error: drive node 1 reports FAULT")
    assert "statusword 0x" in line and "EMCY 0x2310" in line
    kpis, suite, properties = report(tmp_path, done)
    assert kpis["status"] == "failed" and kpis["ticks"] > 0
    assert kpis["stop_reason"].startswith("error: DriveFaultError")
    error = assert_error_case(suite, "DriveFaultError", line)
    assert "0x2310" in error.get("message", "")
    assert properties["status"] == "failed" and properties["faults.emcy"] == str(
        kpis["faults"]["emcy"])


def test_a_bench_safety_stop_and_a_bench_fault_are_reported(tmp_path, capfd, monkeypatch):
    (tmp_path / "tight.toml").write_text("[safety]\nmax_total_va = 100.0\n"
                                         "max_total_va_ms = 100.0\n")
    done = hil(tmp_path, "bench", "run", "--controller", "bc", "--cycles", "1", "--config",
               "tight.toml", "--out", "b.mcap", "--json", "--junit", "report.xml")
    assert done.returncode == 2
    line = one_error_line(done, "hil: error: safety stop at t=")
    kpis, suite, properties = report(tmp_path, done)
    assert kpis["status"] == "stopped" and kpis["J2_VA"] > 100
    assert_error_case(suite, "SafetyStopError", line)
    assert properties["J2_VA"] == str(kpis["J2_VA"]) and properties["mcap"] == "b.mcap"
    assert properties["faults.link_losses"] == "0"

    (tmp_path / "faults.toml").write_text('[faults]\nschedule = ["exception@2:code=2,unit=2"]\n')
    monkeypatch.chdir(tmp_path)
    done = hil_here(capfd, "bench", "run", "--controller", "bc", "--cycles", "1", "--config",
                    "faults.toml", "--out", "f.mcap", "--json", "--junit", "fault.xml")
    assert done.returncode == 2
    line = one_error_line(done, "hil: error: ")
    assert "exception 0x02 (illegal data address)" in line
    kpis, suite, properties = report(tmp_path, done, "fault.xml")
    assert kpis["status"] == "failed" and kpis["stop_reason"].startswith("error: ")
    assert_error_case(suite, "DeviceError", line)
    assert properties["status"] == "failed" and properties["mcap"] == "f.mcap"


def test_a_disturbed_bench_run_is_an_error_case_with_exit_3(tmp_path, capfd):
    (tmp_path / "faults.toml").write_text('[faults]\nschedule = ["freeze@6-8:device=meter"]\n')
    done = hil_here(capfd, "bench", "run", "--controller", "bc", "--duration", "10",
                    "--config", "faults.toml", "--out", "d.mcap", "--json", "--junit",
                    "report.xml", cwd=tmp_path)
    assert done.returncode == 3
    line = one_error_line(done, "hil: run disturbed (completed): stale_readings 1")
    kpis, suite, properties = report(tmp_path, done)
    assert kpis["status"] == "disturbed" and kpis["stop_reason"] == "completed"
    assert_error_case(suite, "RunDisturbed", line)
    assert properties["faults.stale_readings"] == "1" and properties["disturbed"] == "true"


@pytest.mark.parametrize("command", [
    ["servo", "run", "--controller", "pid", "--duration", "1000"],
    ["bench", "run", "--controller", "bc", "--cycles", "1000"],
])
def test_ctrl_c_gives_the_report_of_an_interrupted_run(tmp_path, command):
    session = tmp_path / "run.mcap"
    proc = subprocess.Popen([sys.executable, "-c", AT_A_TERMINAL, *command, "--out",
                             str(session), "--json", "--junit", "report.xml"], cwd=tmp_path,
                            env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while (not session.exists() or session.stat().st_size < 100_000) and \
                time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    done = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    assert done.returncode == 130
    line = one_error_line(done, "hil: interrupted by SIGINT after ")
    kpis, suite, properties = report(tmp_path, done)
    assert kpis["status"] == "interrupted" and kpis["stop_reason"] == "signal SIGINT"
    assert kpis["mcap"] == str(session) and kpis["controller"] == command[3]
    assert_error_case(suite, "RunInterruptedError", line)
    assert properties["status"] == "interrupted"


def test_a_run_that_cannot_start_still_writes_its_report(tmp_path, capfd, monkeypatch):
    monkeypatch.chdir(tmp_path)
    done = hil_here(capfd, "servo", "run", "--controller", "missing.py:Nope", "--json",
                    "--junit", "report.xml")
    assert done.returncode == 2
    line = one_error_line(done, "hil: error: ")
    assert "no such file 'missing.py'" in line
    kpis, suite, properties = report(tmp_path, done)
    assert kpis == {"controller": "missing.py:Nope", "mcap": None, "stop_reason": None,
                    "status": "failed", "error": line.removeprefix("hil: error: ")}
    assert_error_case(suite, "ConfigError", line)
    assert properties["status"] == "failed"
    assert not list(tmp_path.glob("**/*.mcap"))  # nothing ran
