"""What the user configures is what runs, run for real: the drive a ``[bus]`` table names, a
current limit that only tightens (the config's, a flag's, the drive's own 0x6073 / 0x6072), and
the warning a raised limit leaves. Against hil's emulator over socketcand and against a
CiA 402 slave hil did not write (canopen's LocalNode, tests/drive_slave.py). Each setting is
run once from a ``hil`` process; more cases of it (other values, the errors) run the command
line in this process (:func:`hil_here`), from the same folder."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from hil import api
from hil.core.recording.reader import read_session
from tests.cli import hil_here
from tests.drive_slave import RATED_MA, serve
from tests.served_here import drive_served_here

pytestmark = [pytest.mark.slow]

NODE = 3


def hil(cwd: Path, *argv: str) -> subprocess.CompletedProcess[str]:
    """``hil`` as a user runs it, from a folder outside the repository."""
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.run([sys.executable, "-m", "hil", *argv], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def events(path: str, kind: str) -> list[dict]:
    return [m for _, m in read_session(path).topic("/events") if m["kind"] == kind]


def test_a_bus_in_the_config_file_is_the_drive_that_runs(tmp_path, capfd, monkeypatch):
    """[bus] naming a socketcand gateway, no --drive: the run reaches that drive, in lockstep
    over the wire; a gateway nobody serves is a one-line error, never the emulator."""
    with drive_served_here() as drive:
        host, port = drive.url.removeprefix("socketcand://").split(":")
        config = tmp_path / "drive.toml"
        config.write_text(f'[bus]\ninterface = "socketcand"\n[bus.options]\nhost = "{host}"\n'
                          f"port = {port}\n")
        run = hil(tmp_path, "servo", "run", "--controller", "pid", "--config", str(config),
                  "--duration", "0.2", "--json", "--out", "bus.mcap")
        assert run.returncode == 0, run.stderr
        kpis = json.loads(run.stdout)
        assert kpis["drive"] == f"{drive.url}/can0" and kpis["clock"] == "sim"
        assert kpis["ticks"] == 400
    nobody = tmp_path / "nobody.toml"
    nobody.write_text('[bus]\ninterface = "socketcand"\n[bus.options]\nhost = "127.0.0.1"\n'
                      "port = 1\n")
    monkeypatch.chdir(tmp_path)
    for realtime in ([], ["--realtime"]):
        run = hil_here(capfd, "servo", "run", "--controller", "pid", "--config", str(nobody),
                       "--duration", "0.2", "--out", "none.mcap", *realtime)
        assert run.returncode == 2
        assert run.stderr == ("hil: error: cannot connect to socketcand at 127.0.0.1:1: "
                              "Connection refused\n")
        assert not (tmp_path / "none.mcap").exists()


def test_the_config_current_limit_holds_and_a_flag_only_lowers_it(tmp_path, capfd,
                                                                  monkeypatch):
    config = tmp_path / "drive.toml"
    config.write_text("[master]\ncurrent_limit_mA = 300\n")
    base = ["servo", "run", "--controller", "pid", "--config", str(config), "--reference",
            "hold:position=30", "--duration", "0.3", "--json"]
    held = hil(tmp_path, *base, "--out", "held.mcap")
    assert held.returncode == 0, held.stderr
    kpis = json.loads(held.stdout)
    assert kpis["umax_mA"] == 300 and kpis["current_limit_mA"] == 300
    # the controller's bounds are the limit too: it asks for no more than it may have
    assert kpis["peak_current_mA"] == 300 and kpis["peak_requested_mA"] == 300
    monkeypatch.chdir(tmp_path)
    lower = json.loads(hil_here(capfd, *base, "--umax", "200", "--out", "lower.mcap").stdout)
    assert lower["current_limit_mA"] == 200 and lower["peak_current_mA"] == 200
    refused = hil_here(capfd, *base, "--umax", "500", "--out", "refused.mcap")
    assert refused.returncode == 2 and json.loads(refused.stdout)["status"] == "failed"
    assert refused.stderr == (
        f"hil: error: --umax 500 mA is above the configured current limit "
        f"(master.current_limit_mA = 300 mA, --config {config}): a flag may lower it, not raise "
        "it; --allow-higher-current raises it (recorded)\n")
    raised = hil_here(capfd, *base, "--umax", "500", "--allow-higher-current", "--out",
                      "raised.mcap")
    assert raised.returncode == 0, raised.stderr
    assert json.loads(raised.stdout)["current_limit_mA"] == 500
    assert "hil: warning: --umax 500 mA raises the configured current limit of 300 mA" \
        in raised.stderr
    [event] = events(str(tmp_path / "raised.mcap"), "current.limit_raised")
    assert event["level"] == "warning"


@pytest.mark.parametrize(("text", "named"), [
    ('[master]\ncurrent_limit_mA = "300"\n',
     "key 'master.current_limit_mA' must be a number, got a string '300'"),
    ("[master]\ncurrent_limit_mA = 0.3\n",  # amperes, surely: refused when read
     "key 'master.current_limit_mA' = 0.3: 0.3 mA is below 1 mA"),
    ("[master]\ncurrent_limit_mA = 3\n[emulator]\nrated_current_mA = 4000\n",
     "drive node 1: current limit 3 mA, the smallest of the run's 3 mA"),
])
def test_a_current_limit_that_cannot_hold_is_refused(tmp_path, capfd, monkeypatch, text, named):
    monkeypatch.chdir(tmp_path)
    config = tmp_path / "drive.toml"
    config.write_text(text)
    run = hil_here(capfd, "servo", "run", "--controller", "pid", "--config", str(config),
                   "--duration", "0.1", "--out", "x.mcap")
    assert run.returncode == 2 and named in run.stderr and len(run.stderr.splitlines()) == 1


def test_the_drives_own_max_current_tightens_the_chain_and_its_max_torque_comes_back(tmp_path):
    """A drive hil did not write, whose 0x6073 allows 300 mA (150 per mille of 2 A): the run's
    1000 mA are cut to 300, every link is recorded, and its 0x6072 is its own again after."""
    url = f"virtual://limit-{uuid.uuid4().hex}"
    network, slave = serve(url, NODE, max_current_permille=150)
    try:
        kpis = api.run_servo(Kick, drive=url, node=NODE, reference="hold:position=0",
                             duration_s=0.1, out=str(tmp_path / "slave.mcap"))
    finally:
        network.disconnect()
    assert kpis["current_limit_mA"] == 300 and kpis["umax_mA"] == 300
    assert kpis["peak_requested_mA"] == Kick.ASKED and kpis["peak_current_mA"] == 300
    assert kpis["clamped_commands"] == 4  # the ticks of t < 2 ms
    assert max(abs(entry_ma) for entry_ma in _slave_currents(slave)) <= 300
    [event] = events(kpis["mcap"], "drive.current_limit")
    assert event["data"] == {"applied_mA": 300.0, "run_mA": 1000.0,
                             "drive_max_current_mA": 300.0,
                             "drive_max_torque_mA": float(RATED_MA)}
    configured = events(kpis["mcap"], "drive.configured")[0]["data"]
    assert configured["current_limit"]["applied_mA"] == 300.0
    # 0x6072: 150 per mille for the run, then the slave's own 1000 again
    assert [int.from_bytes(data, "little") for index, _, data in slave.writes
            if index == 0x6072] == [150, 1000]
    assert slave.value(0x6072) == 1000


class Kick:
    """Asks for far more current than any link allows, for the first 2 ms only."""

    ASKED = 5000.0

    def __init__(self, reference, params):
        self.reference = reference

    def step(self, position_deg, t_s):
        return self.ASKED if t_s < 0.002 else 0.0


def _slave_currents(slave) -> list[float]:
    """The currents the slave reported in its TPDO2, mA."""
    return [int.from_bytes(bytes.fromhex(entry["tpdo2"])[4:6], "little", signed=True)
            * RATED_MA / 1000 for entry in slave.log if entry["tpdo2"]]


def test_print_config_from_outside_shows_every_setting_and_runs_nothing(tmp_path):
    config = tmp_path / "drive.toml"
    config.write_text("[master]\ncurrent_limit_mA = 800\neds = \"drive.eds\"\n")
    shown = hil(tmp_path, "servo", "run", "--controller", "mpc", "--config", str(config),
                "--umax", "300", "--print-config", "--json", "--out", "never.mcap")
    assert shown.returncode == 0, shown.stderr
    settings = json.loads(shown.stdout)
    assert settings["master.current_limit_mA"] == {"value": 300.0, "origin": "--umax"}
    assert settings["master.eds"] == {"value": str(tmp_path / "drive.eds"),
                                      "origin": f"--config {config}"}
    assert settings["master.mode"] == {"value": "cst", "origin": "hil/configs/drive.toml"}
    assert settings["run.controller"] == {"value": "mpc", "origin": "--controller"}
    assert not (tmp_path / "never.mcap").exists()
    text = hil(tmp_path, "bench", "run", "--controller", "bc", "--hp", "14", "--print-config")
    assert text.returncode == 0 and "hp_s = 14" in text.stdout and "# --hp" in text.stdout


@pytest.mark.parametrize(("argv", "line", "outside"), [
    (["--controler", "pid"], "hil servo run: error: unrecognized arguments: --controler pid "
     "(--controler: did you mean --controller?) (see 'hil servo run --help')", True),
    (["--controller", "pid", "--umax", "0.3"], "hil servo run: error: argument --umax: 0.3 mA "
     "is below 1 mA: the value is in mA (0.3 A would be 300 mA) (see 'hil servo run --help')",
     False),
    (["--controller", "pid", "--duration", "10ms"], "hil servo run: error: argument "
     "--duration: takes a number of seconds, without its unit: '10ms' is 0.01 (write 0.01) "
     "(see 'hil servo run --help')", False),
    (["--controller", "pid", "--umax", "2A"], "hil servo run: error: argument --umax: takes a "
     "number of mA, without its unit: '2A' is 2000 (write 2000) (see 'hil servo run --help')",
     False),
])
def test_a_typo_or_another_unit_is_one_line_that_says_what_was_meant(tmp_path, capfd,
                                                                     monkeypatch, argv, line,
                                                                     outside):
    """The parser's refusals: one from a ``hil`` process, the others in this one."""
    if outside:
        run = hil(tmp_path, "servo", "run", *argv, "--out", "never.mcap")
    else:
        monkeypatch.chdir(tmp_path)
        run = hil_here(capfd, "servo", "run", *argv, "--out", "never.mcap")
    assert run.returncode == 2 and run.stderr == line + "\n"
    assert not (tmp_path / "never.mcap").exists()


def test_an_eds_beside_the_config_file_is_the_one_checked(tmp_path, capfd):
    """[master] eds is read from the config file's folder, --eds from the working folder;
    the run checks the drive against it before anything is written."""
    folder = tmp_path / "bench"
    folder.mkdir()
    written = hil_here(capfd, "emulate", "drive", "--write-eds", "drive.eds", cwd=folder)
    assert written.returncode == 0, written.stderr
    config = folder / "drive.toml"
    config.write_text('[master]\neds = "drive.eds"\n')
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    run = hil(elsewhere, "servo", "run", "--controller", "pid", "--config", str(config),
              "--duration", "0.1", "--out", "eds.mcap")
    assert run.returncode == 0, run.stderr
    drive = json.loads(read_session(str(elsewhere / "eds.mcap")).metadata["drive"]["json"])
    assert drive["eds"]["path"] == str(folder / "drive.eds")
    missing = hil_here(capfd, "servo", "run", "--controller", "pid", "--eds", "drive.eds",
                       "--duration", "0.1", "--out", "none.mcap", cwd=elsewhere)
    assert missing.returncode == 2 and str(elsewhere / "drive.eds") in missing.stderr


@pytest.mark.realtime
def test_the_emulator_process_of_a_real_time_run_gets_every_layer(tmp_path):
    """--realtime against `emulated` starts the emulator in a process of its own: it is given
    the run's effective tables, a program's overrides and flags included, not the file alone."""
    # the link made patient (400 cycles, 200 ms): what is checked is the emulator's tables,
    # not whether a Python process on a shared VM answers every 500 us (a fresh clone once
    # lost 20 cycles in a row here)
    kpis = api.run_servo("pid", realtime=True, duration_s=0.3, out=str(tmp_path / "rt.mcap"),
                         drive_overrides={"emulator": {"max_torque_permille": 500},
                                          "master": {"stale_cycles": 400}})
    assert kpis["clock"] == "realtime" and kpis["current_limit_mA"] == 500.0
    [event] = events(kpis["mcap"], "drive.current_limit")
    assert event["data"]["drive_max_torque_mA"] == 500.0
