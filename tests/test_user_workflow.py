"""What a user does, from a folder outside the repository: their own controllers in their own
file, run through the command line with FILE.py:Class and --param, and their own tests using
the hil_bench and hil_drive fixtures with a plain ``python -m pytest``."""

import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

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


def run_pytest(folder, *args):
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "--rootdir", str(folder), *args], cwd=folder, env=user_env(),
                          capture_output=True, text=True, timeout=300)


def hil(folder, *args, timeout=120):
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=folder, env=user_env(),
                          capture_output=True, text=True, timeout=timeout)


def test_users_tests_pass_with_plain_pytest_and_the_installed_plugin(tmp_path):
    folder = user_folder(tmp_path)
    out = run_pytest(folder, str(folder))
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "3 passed" in out.stdout


def test_a_failing_user_test_names_its_session_files(tmp_path):
    folder = user_folder(tmp_path)
    (folder / "test_fails.py").write_text(
        "from my_controllers import PdPosition\n\n"
        "def test_too_strict(hil_drive):\n"
        "    kpis = hil_drive.run(PdPosition, duration_s=0.2)\n"
        "    assert kpis['rms_error_deg'] < 1e-9\n")
    out = run_pytest(folder, "test_fails.py")
    assert out.returncode == 1
    assert "hil sessions" in out.stdout and "servo-1.mcap" in out.stdout


def test_users_controllers_run_through_the_cli_with_params(tmp_path):
    folder = user_folder(tmp_path)
    bench = hil(folder, "bench", "run", "--controller", "my_controllers.py:ThresholdRelays",
                "--param", "on_below=75", "--cycles", "1", "--out", "b.mcap", "--json")
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


def test_params_change_what_the_users_controller_does(tmp_path):
    folder = user_folder(tmp_path)
    runs = [json.loads(hil(folder, "servo", "run", "--controller",
                           "my_controllers.py:PdPosition", "--param", f"kp={kp}", "--duration",
                           "0.5", "--reference", "sine:amplitude=2,frequency=1",
                           "--json").stdout) for kp in (50, 400)]
    assert runs[1]["rms_error_deg"] < runs[0]["rms_error_deg"] / 2  # stiffer gain, less error


def test_a_violated_limit_exits_1_with_a_junit_failure_and_a_loose_one_exits_0(tmp_path):
    folder = user_folder(tmp_path)
    args = ["servo", "run", "--controller", "my_controllers.py:PdPosition", "--duration", "0.5",
            "--reference", "sine:amplitude=2,frequency=1"]
    strict = hil(folder, *args, "--limit", "rms_error_deg<=0.001", "--junit", "strict.xml")
    assert strict.returncode == 1
    assert "hil: limit violated: rms_error_deg<=0.001: measured" in strict.stderr
    suite = ET.parse(folder / "strict.xml").getroot().find("testsuite")
    assert suite is not None and suite.get("failures") == "1"
    assert suite.find("testcase/failure") is not None
    loose = hil(folder, *args, "--limit", "rms_error_deg<=1", "--limit", "ticks>=1000",
                "--junit", "loose.xml")
    assert loose.returncode == 0, loose.stderr
    suite = ET.parse(folder / "loose.xml").getroot().find("testsuite")
    assert suite is not None and suite.get("tests") == "2" and suite.get("failures") == "0"


LEAVES_A_RELAY_ON = '''
from drivers.bench.modbus import ModbusBenchDriver, ModbusLink, parse_bus_url
from hil.bench.config import load_bench_config

def test_switches_p1_behind_the_safety_layers_back(hil_bench):
    config = load_bench_config()
    driver = ModbusBenchDriver(ModbusLink(parse_bus_url(hil_bench.url), 0.5, 2), config.map)
    driver.write_relay("P1", True)
    driver.close()
'''

USES_THE_GIVEN_BENCH = '''
import os

def test_points_at_the_given_bench(hil_bench):
    assert hil_bench.url == os.environ["BENCH_URL"] and not hil_bench.emulated
    assert hil_bench.driver.read_levels()["q1"] > 0
'''


def test_teardown_fails_a_test_that_leaves_the_bench_unsafe(tmp_path):
    folder = user_folder(tmp_path)
    (folder / "test_unsafe.py").write_text(LEAVES_A_RELAY_ON)
    out = run_pytest(folder, "test_unsafe.py")
    assert out.returncode == 1
    assert "relays P1 were left off their safe level" in out.stdout


def test_hil_bench_option_points_the_fixture_at_a_given_bench(tmp_path, monkeypatch):
    from hil.emulator_process import start_bench_emulator

    folder = user_folder(tmp_path)
    (folder / "test_given.py").write_text(USES_THE_GIVEN_BENCH)
    with start_bench_emulator() as bench:
        monkeypatch.setenv("BENCH_URL", bench.url)
        out = run_pytest(folder, "test_given.py", "--hil-bench", bench.url)
    assert out.returncode == 0, out.stdout[-2000:]


def test_json_output_of_an_eec_run_is_json_alone(tmp_path):
    """A script reads --json from stdout: nothing else may be printed there (the MILP solver's
    banner included)."""
    run = hil(tmp_path, "bench", "run", "--controller", "eec", "--cycles", "1", "--out",
              "e.mcap", "--json", timeout=300)
    assert run.returncode == 0, run.stderr
    kpis = json.loads(run.stdout)
    assert kpis["controller"] == "eec" and kpis["solves_at_limit"] == 0


def test_a_split_servo_session_is_one_session_to_report(tmp_path):
    """--split-duration writes a numbered series; report takes its name, first file or folder;
    the drive topics are CDR by default and JSON with --encoding json."""
    folder = tmp_path / "lab"
    (folder / "runs").mkdir(parents=True)
    out = hil(folder, "servo", "run", "--controller", "pid", "--duration", "2",
              "--split-duration", "0.5", "--out", "runs/long.mcap", "--json")
    assert out.returncode == 0, out.stderr
    kpis = json.loads(out.stdout)
    assert kpis["mcap"] == "runs/long_000.mcap"
    names = sorted(p.name for p in (folder / "runs").iterdir())
    assert names == [f"long_{i:03d}.mcap" for i in range(len(names))] and len(names) >= 4
    reports = []
    for spelled in ("runs/long.mcap", "runs/long_000.mcap", "runs"):
        report = hil(folder, "report", spelled, "--json")
        assert report.returncode == 0, report.stderr
        reports.append(json.loads(report.stdout))
    assert all(r["topics"] == reports[0]["topics"] for r in reports)
    assert reports[0]["topics"]["/drive/feedback"] == kpis["ticks"] == 4000
    assert len(reports[0]["files"]) == len(names) and reports[0]["damage"] == []
    assert reports[0]["encodings"]["/drive/feedback"] == "cdr"
    assert reports[0]["encodings"]["/events"] == "json"

    plain = hil(folder, "servo", "run", "--controller", "pid", "--duration", "0.5",
                "--encoding", "json", "--out", "plain.mcap")
    assert plain.returncode == 0, plain.stderr
    report = json.loads(hil(folder, "report", "plain.mcap", "--json").stdout)
    assert report["encodings"]["/drive/feedback"] == "json"
    bad = hil(folder, "servo", "run", "--controller", "pid", "--split-size", "0")
    assert bad.returncode == 2 and "--split-size" in bad.stderr
