"""What a user does, from a folder outside the repository: their own controllers in their own
file, run through the command line with FILE.py:Class and --param, and their own tests using
the hil_bench and hil_drive fixtures with a plain ``python -m pytest``. A user's controller
runs as ``hil`` processes; more cases (other params, limits, a report's other spellings) run the
command line in this process (:func:`hil_here`), from the same folder."""

import json
import math
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from hil import api
from tests.cli import NOT_A_USERS_PLUGINS, hil_here
from tests.drive_processes import patient_watchdogs
from tests.pymodbus_bench import short_config

pytestmark = [pytest.mark.slow]

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def user_folder(tmp_path):
    folder = tmp_path / "my_lab"
    folder.mkdir()
    for name in ("my_controllers.py", "test_my_controllers.py"):
        shutil.copy(EXAMPLES / name, folder / name)
    return folder


def user_env():
    """The environment of a user's shell: hil installed, the repository not on the path."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


def run_pytest(folder, *args, env=None):
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           *NOT_A_USERS_PLUGINS, "--rootdir", str(folder), *args], cwd=folder,
                          env={**user_env(), **(env or {})}, capture_output=True, text=True,
                          timeout=300)


def hil(folder, *args, timeout=120):
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=folder, env=user_env(),
                          capture_output=True, text=True, timeout=timeout)


def failure_section(stdout, test):
    """What ``pytest -q`` printed about ``test``'s failure: from its header to the next one."""
    after = stdout.split(f"_ {test} _", 1)[1]
    return after.split("\n_", 1)[0]


#: the hil_bench fixture's runs against its own emulator go over the wire on the run's time
OVER_THE_WIRE = '''
from hil.core.recording.reader import read_session


def test_runs_in_lockstep_on_the_fixtures_own_emulator(hil_bench):
    assert hil_bench.driver.read_levels()["q1"] > 0     # on the wall clock, before
    kpis = hil_bench.run("bc", cycles=1)
    assert kpis["status"] == "completed"
    metadata = read_session(hil_bench.sessions[0]).metadata
    assert metadata["session"]["clock"] == "sim"
    assert metadata["bench"]["url"] == hil_bench.url
    assert "let go at plant time 28.00 s" in hil_bench.emulator.stderr_tail()
    assert hil_bench.driver.read_levels()["q1"] > 0     # and after
'''


#: the hil_drive fixture in every mode: a homing, a profile move, a CSP run homed first
EVERY_MODE = '''
def test_homes_moves_and_runs_csp_from_home(hil_drive):
    home = hil_drive.home(method=37, offset_deg=10.0)
    assert home["reached"] and abs(home["position_deg"] - 10.0) < 0.01
    move = hil_drive.move(40.0, velocity_deg_s=180.0)
    assert move["reached"] and abs(move["error_deg"]) <= 0.1
    run = hil_drive.run("setpoint", reference="hold:position=40", duration_s=0.2, home=True,
                        drive_overrides={"master": {"mode": "csp"},
                                         "homing": {"method": 37, "offset_deg": 40.0}})
    assert run["set_point"] == "position" and run["max_error_deg"] < 0.1
    assert [s.rsplit("/", 1)[-1] for s in hil_drive.sessions] == [
        "home-1.mcap", "move-2.mcap", "servo-3.mcap"]
'''


@pytest.fixture(scope="module")
def passing_run(tmp_path_factory):
    """One plain ``pytest`` run of a user's tests that pass (each start of pytest and hil's
    plugin costs CPU): the examples' tests, :data:`OVER_THE_WIRE` and :data:`EVERY_MODE`. The
    finished run and its test cases (name: the case's element) from ``results.xml``."""
    folder = user_folder(tmp_path_factory.mktemp("users"))
    (folder / "test_over_the_wire.py").write_text(OVER_THE_WIRE)
    (folder / "test_every_mode.py").write_text(EVERY_MODE)
    out = run_pytest(folder, str(folder), "--junitxml", "results.xml")
    cases = {case.get("name"): case
             for case in ET.parse(folder / "results.xml").getroot().iter("testcase")}
    return out, cases


def passed(case):
    """Whether a junit test case passed: no failure, error or skip in it."""
    return not [child.tag for child in case if child.tag in ("failure", "error", "skipped")]


def test_users_tests_pass_with_plain_pytest_and_the_installed_plugin(passing_run):
    """The examples' tests, and one more that looks at how the fixture's runs go."""
    out, cases = passing_run
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "5 passed" in out.stdout  # with test_every_mode.py's one
    assert len(cases) == 5 and all(passed(case) for case in cases.values())
    # each run's KPIs are the test case's properties; the emulators' runs are lockstep
    properties = {name: {p.get("name"): p.get("value") for p in case.iter("property")}
                  for name, case in cases.items()}
    servo = properties["test_pd_tracks_a_slow_sine_through_the_drive"]
    assert servo["servo-1.clock"] == "sim" and servo["servo-1.status"] == "completed"
    assert servo["servo-1.passed"] == "true" and float(servo["servo-1.rms_error_deg"]) < 0.5
    bench = properties["test_threshold_relays_keep_the_levels_in_range"]
    assert bench["bench-1.level_violations"] == "0" and bench["bench-1.status"] == "completed"
    assert bench["bench-1.mcap"].endswith("bench-1.mcap")
    assert properties["test_the_bench_driver_switches_a_relay_and_reads_power"] == {}  # no run


def test_the_drive_fixture_homes_moves_and_runs_every_mode(passing_run):
    out, cases = passing_run
    case = cases["test_homes_moves_and_runs_csp_from_home"]
    assert case.get("classname") == "test_every_mode" and passed(case), \
        out.stdout[-3000:] + out.stderr[-2000:]


LEAVES_A_RELAY_ON = '''
from hil.drivers.bench.modbus import ModbusBenchDriver, ModbusLink, parse_bus_url
from hil.bench.config import load_bench_config

def test_switches_p1_behind_the_safety_layers_back(hil_bench):
    config = load_bench_config()
    driver = ModbusBenchDriver(ModbusLink(parse_bus_url(hil_bench.url), 0.5, 2), config.map)
    driver.write_relay("P1", True)
    driver.close()
'''


def test_a_failing_user_test_names_its_session_files_and_an_unsafe_bench_fails_its_test(
        tmp_path):
    """Two failures in one pytest run: a test whose assertion fails names its session files;
    the fixture's teardown fails a test that leaves the bench unsafe."""
    folder = user_folder(tmp_path)
    (folder / "test_fails.py").write_text(
        "from my_controllers import PdPosition\n\n"
        "def test_too_strict(hil_drive):\n"
        "    kpis = hil_drive.run(PdPosition, duration_s=0.2)\n"
        "    assert kpis['rms_error_deg'] < 1e-9\n")
    (folder / "test_unsafe.py").write_text(LEAVES_A_RELAY_ON)
    out = run_pytest(folder, "test_fails.py", "test_unsafe.py")
    assert out.returncode == 1
    strict = failure_section(out.stdout, "test_too_strict")
    assert "hil sessions" in strict and "servo-1.mcap" in strict
    unsafe = failure_section(out.stdout,
                             "ERROR at teardown of test_switches_p1_behind_the_safety_layers_back")
    assert "relays P1 were left off their safe level" in unsafe


def test_users_controllers_run_through_the_cli_with_params(tmp_path):
    folder = user_folder(tmp_path)
    # a 4 s machining cycle: what runs is the user's class with its params, not a long cycle
    bench = hil(folder, "bench", "run", "--controller", "my_controllers.py:ThresholdRelays",
                "--param", "on_below=75", "--cycles", "1", "--config", str(short_config(folder)),
                "--out", "b.mcap", "--json")
    assert bench.returncode == 0, bench.stderr
    kpis = json.loads(bench.stdout)
    assert kpis["controller"] == "my_controllers.py:ThresholdRelays"
    assert kpis["level_violations"] == 0 and (folder / "b.mcap").is_file()
    servo = hil(folder, "servo", "run", "--controller", "my_controllers.py:PdPosition",
                "--param", "kp=300", "--param", "kd=6", "--reference",
                "sine:amplitude=2,frequency=1", "--duration", "0.5", "--out", "s.mcap",
                "--json")
    assert servo.returncode == 0, servo.stderr
    assert json.loads(servo.stdout)["rms_error_deg"] < 0.5


def test_params_change_what_the_users_controller_does(tmp_path, capfd, monkeypatch):
    folder = user_folder(tmp_path)
    monkeypatch.chdir(folder)
    runs = [json.loads(hil_here(capfd, "servo", "run", "--controller",
                                "my_controllers.py:PdPosition", "--param", f"kp={kp}",
                                "--duration", "0.5", "--reference",
                                "sine:amplitude=2,frequency=1", "--json").stdout)
            for kp in (50, 400)]
    assert runs[1]["rms_error_deg"] < runs[0]["rms_error_deg"] / 2  # stiffer gain, less error


def test_a_violated_limit_exits_1_with_a_junit_failure_and_a_loose_one_exits_0(tmp_path, capfd,
                                                                            monkeypatch):
    folder = user_folder(tmp_path)
    monkeypatch.chdir(folder)
    args = ["servo", "run", "--controller", "my_controllers.py:PdPosition", "--duration", "0.5",
            "--reference", "sine:amplitude=2,frequency=1"]
    strict = hil_here(capfd, *args, "--limit", "rms_error_deg<=0.001", "--junit", "strict.xml")
    assert strict.returncode == 1
    assert "hil: limit violated: rms_error_deg<=0.001: measured" in strict.stderr
    suite = ET.parse(folder / "strict.xml").getroot().find("testsuite")
    assert suite is not None and suite.get("failures") == "1"
    assert suite.find("testcase/failure") is not None
    loose = hil_here(capfd, *args, "--limit", "rms_error_deg<=1", "--limit", "ticks>=1000",
                     "--junit", "loose.xml")
    assert loose.returncode == 0, loose.stderr
    suite = ET.parse(folder / "loose.xml").getroot().find("testsuite")
    assert suite is not None and suite.get("tests") == "3" and suite.get("failures") == "0"
    assert [case.get("name") for case in suite.findall("testcase")] == [
        "rms_error_deg<=1", "ticks>=1000", "run"]


# generous watchdogs: on a loaded machine a wall-clock run over socketcand may miss many
# cycles; only what these tests look at may end a run
LOADED_MACHINE_DRIVE = patient_watchdogs("rx_timeout_us = 5000\n")

RUNS_ON_THE_GIVEN_DRIVE = '''
import os

from hil.core.recording.reader import read_session
from my_controllers import PdPosition

CONFIG = os.environ["DRIVE_CONFIG"]
GAINS = {"kp": 300, "kd": 6}


def test_moves_the_axis_away(hil_drive):
    kpis = hil_drive.run(PdPosition, GAINS, duration_s=0.5, drive_config=CONFIG,
                         reference="trapezoid:stroke=90,speed=30,acceleration=2000")
    assert kpis["clock"] == "realtime" and kpis["stop_reason"] == "completed"


def test_starts_where_the_axis_stands(hil_drive):
    kpis = hil_drive.run(PdPosition, GAINS, duration_s=0.3, drive_config=CONFIG,
                         reference="sine:amplitude=2,frequency=1")
    assert kpis["clock"] == "realtime" and kpis["stop_reason"] == "completed"
    start = read_session(hil_drive.sessions[0]).arrays("/drive/feedback")["position_deg"][0]
    print(f"started at {start:.3f} deg, max error {kpis['max_error_deg']:.3f} deg")
    assert 45 < start % 360 < 315  # far from 0: a run from 0 would have been stopped
    assert kpis["max_error_deg"] < 20
'''

FAULTED_DRIVE = '''
from my_controllers import PdPosition


def test_a_faulted_drive_fails_the_test(hil_drive):
    hil_drive.run(PdPosition, duration_s=0.2)


def test_a_fault_is_reset_when_asked(hil_drive):
    kpis = hil_drive.run(PdPosition, duration_s=0.2, reset_fault=True)
    assert kpis["ticks"] > 0
'''


@pytest.mark.realtime
def test_hil_drive_option_runs_on_the_wall_clock_from_where_the_axis_stands(tmp_path):
    """``--hil-drive URL``: each test's runs follow the wall clock, start where the axis
    stands (the first test leaves it about 70 deg away), and put their KPIs in --junitxml."""
    folder = user_folder(tmp_path)
    (folder / "test_given_drive.py").write_text(RUNS_ON_THE_GIVEN_DRIVE)
    config = folder / "drive.toml"
    config.write_text(LOADED_MACHINE_DRIVE)
    with api.start_drive_emulator(str(config), harden=True) as drive:
        out = run_pytest(folder, "test_given_drive.py", "-s", "--hil-drive", drive.url,
                         "--junitxml", "results.xml", env={"DRIVE_CONFIG": str(config)})
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    cases = {case.get("name"): {p.get("name"): p.get("value") for p in case.iter("property")}
             for case in ET.parse(folder / "results.xml").getroot().iter("testcase")}
    for name in ("test_moves_the_axis_away", "test_starts_where_the_axis_stands"):
        properties = cases[name]
        assert properties["servo-1.clock"] == "realtime", properties
        assert properties["servo-1.status"] in ("completed", "disturbed")
        assert properties["servo-1.mcap"].endswith("servo-1.mcap")
        assert math.isfinite(float(properties["servo-1.rms_error_deg"]))
        assert properties["servo-1.drive"] == drive.url


@pytest.mark.realtime
def test_a_faulted_drive_fails_its_test_with_one_line_and_is_reset_only_when_asked(tmp_path):
    folder = user_folder(tmp_path)
    (folder / "test_faulted.py").write_text(FAULTED_DRIVE)
    config = folder / "drive.toml"
    config.write_text(LOADED_MACHINE_DRIVE)
    with api.start_drive_emulator(str(config), faults=["emcy@0:code=0x2310"],
                                  harden=True) as drive:
        out = run_pytest(folder, "test_faulted.py", "--hil-drive", drive.url,
                         "--junitxml", "results.xml")
    assert out.returncode == 1, out.stdout[-3000:]
    assert "1 failed, 1 passed" in out.stdout
    section = out.stdout.split("test_a_faulted_drive_fails_the_test _")[1].splitlines()
    # the failure is the error's one line (no frames of hil's code), then the sessions
    assert section[1].startswith("DriveFaultError: drive node 1 is in FAULT"), section[:4]
    assert "0x2310" in section[1] and "hil sessions" in section[2]
    assert "Traceback" not in out.stdout and "drivers/canopen" not in out.stdout
    failure = ET.parse(folder / "results.xml").getroot().find(".//testcase/failure")
    assert failure is not None and failure.get("message", "").startswith("DriveFaultError: ")


USES_THE_GIVEN_BENCH = '''
import os

def test_points_at_the_given_bench(hil_bench):
    assert hil_bench.url == os.environ["BENCH_URL"] and not hil_bench.emulated
    assert hil_bench.driver.read_levels()["q1"] > 0
'''


def test_hil_bench_option_points_the_fixture_at_a_given_bench(tmp_path, monkeypatch):
    from hil.emulator_process import start_bench_emulator

    folder = user_folder(tmp_path)
    (folder / "test_given.py").write_text(USES_THE_GIVEN_BENCH)
    with start_bench_emulator() as bench:
        monkeypatch.setenv("BENCH_URL", bench.url)
        out = run_pytest(folder, "test_given.py", "--hil-bench", bench.url)
    assert out.returncode == 0, out.stdout[-2000:]


def test_a_split_servo_session_is_one_session_to_report(tmp_path, capfd, monkeypatch):
    """--split-duration writes a numbered series; report takes its name, first file or folder;
    the drive topics are CDR by default and JSON with --encoding json."""
    folder = tmp_path / "lab"
    (folder / "runs").mkdir(parents=True)
    out = hil_here(capfd, "servo", "run", "--controller", "pid", "--duration", "2",
                   "--split-duration", "0.5", "--out", "runs/long.mcap", "--json", cwd=folder)
    assert out.returncode == 0, out.stderr
    kpis = json.loads(out.stdout)
    assert kpis["mcap"] == "runs/long_000.mcap"
    names = sorted(p.name for p in (folder / "runs").iterdir())
    assert names == [f"long_{i:03d}.mcap" for i in range(len(names))] and len(names) >= 4
    reports = []
    monkeypatch.chdir(folder)  # the name from a hil process, the other spellings here
    for spelled in ("runs/long.mcap", "runs/long_000.mcap", "runs"):
        report = (hil(folder, "report", spelled, "--json") if spelled == "runs/long.mcap"
                  else hil_here(capfd, "report", spelled, "--json"))
        assert report.returncode == 0, report.stderr
        reports.append(json.loads(report.stdout))
    assert all(r["topics"] == reports[0]["topics"] for r in reports)
    assert reports[0]["topics"]["/drive/feedback"] == kpis["ticks"] == 4000
    assert len(reports[0]["files"]) == len(names) and reports[0]["damage"] == []
    assert reports[0]["encodings"]["/drive/feedback"] == "cdr"
    assert reports[0]["encodings"]["/events"] == "json"

    plain = hil_here(capfd, "servo", "run", "--controller", "pid", "--duration", "0.5",
                     "--encoding", "json", "--out", "plain.mcap")
    assert plain.returncode == 0, plain.stderr
    report = json.loads(hil_here(capfd, "report", "plain.mcap", "--json").stdout)
    assert report["encodings"]["/drive/feedback"] == "json"
    bad = hil_here(capfd, "servo", "run", "--controller", "pid", "--split-size", "0")
    assert bad.returncode == 2 and "--split-size" in bad.stderr
