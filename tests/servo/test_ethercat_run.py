"""CiA 402 over EtherCAT, from the command line run outside the repository: hil's master
(SOEM) on one end of a veth pair in a namespace of the test's own, hil's EtherCAT slave
(``hil emulate drive --ethercat``, a process of its own) on the other. A lockstep run records
the KPIs the same run over CAN records; the scan lists the slaves; a refused SDO, an emergency,
a killed slave and a veth end set down each end the way they end on CAN. Each command runs
from outside at least once; its variants run ``main`` in this process, in the namespace
(``hil_here`` inside ``inside``: the same exit status and output, without an interpreter
start)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil import api
from tests.cli import hil_here
from tests.ethercat_netns import (
    REPO,
    Veth,
    inside,
    slave_on,
    start_slave,
    stop_slave,
    veth_pair,
)

pytest.importorskip("pysoem", reason="the ethercat extra (pysoem) is not installed")

pytestmark = pytest.mark.slow

AXIS_KPIS = ("max_error_deg", "rms_error_deg", "peak_current_mA", "stale_feedback")
KPIS = ("max_error_deg", "rms_error_deg", "cumulative_error_deg", "peak_current_mA", "ticks",
        "stale_feedback", "status")
SHORT_LOCKSTEP = '[master]\nlockstep_timeout_ms = 500\n'


def hil_in(veth: Veth, cwd: Path, *args: str, timeout: float = 180
           ) -> subprocess.CompletedProcess[str]:
    """``hil ARGS`` in the namespace, from ``cwd`` (outside the repository)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(["ip", "netns", "exec", veth.ns, sys.executable, "-m", "hil", *args],
                          cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)


def hil_here_in(veth: Veth, cwd: Path, capsys: pytest.CaptureFixture[str], *args: str
                ) -> subprocess.CompletedProcess[str]:
    """``hil ARGS`` by ``main`` in this process, in the namespace, from ``cwd``, as
    :func:`hil_in` reports it."""
    with inside(veth):
        return hil_here(capsys, *args, cwd=cwd)


def popen_hil_in(veth: Veth, cwd: Path, *args: str) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen(["ip", "netns", "exec", veth.ns, sys.executable, "-m", "hil", *args],
                            cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)


@pytest.mark.parametrize(("mode", "controller", "outside"), [("cst", "pid", True),
                                                          ("csp", "setpoint", False)])
def test_a_lockstep_run_records_the_kpis_the_same_run_over_can_records(tmp_path, capsys, mode,
                                                                        controller, outside):
    """The first case from outside (``outside``), the other in this process."""
    config = tmp_path / "drive.toml"
    config.write_text(f'[master]\nmode = "{mode}"\n')
    with veth_pair() as veth, slave_on(veth):
        argv = ("servo", "run", "--drive", f"ethercat://{veth.master}?slave=1", "--controller",
                controller, "--config", str(config), "--duration", "0.5", "--json",
                "--out", str(tmp_path / "ethercat.mcap"))
        out = hil_in(veth, tmp_path, *argv) if outside else \
            hil_here_in(veth, tmp_path, capsys, *argv)
    assert out.returncode == 0, out.stderr
    over_ethercat = json.loads(out.stdout)
    # the session read back by ``main`` in this process: reading it is not what this tests
    report = hil_here(capsys, "report", over_ethercat["mcap"], "--events")
    assert report.returncode == 0, report.stderr
    events = report.stdout
    # SOEM found the slave's distributed clock: aligned, SYNC0 every cycle
    assert "in OP, working counter 3 a cycle, SYNC0 every 500 us" in events
    over_can = api.run_servo(controller, duration_s=0.5, drive_config=str(config),
                             out=str(tmp_path / "can.mcap"))
    assert over_ethercat["drive"] == f"ethercat://{veth.master}?slave=1"
    assert {k: over_ethercat[k] for k in KPIS} == {k: over_can[k] for k in KPIS}
    assert over_ethercat["ticks"] == 1000 and over_ethercat["stale_feedback"] == 0


def test_the_scan_lists_each_slave_with_identity_modes_and_pdos(tmp_path):
    with veth_pair() as veth, slave_on(veth, "--node", "1", "--node", "2"):
        out = hil_in(veth, tmp_path, "drive", "scan", f"ethercat://{veth.master}", "--json")
    assert out.returncode == 0, out.stderr
    nodes = json.loads(out.stdout)["nodes"]
    assert [node["node_id"] for node in nodes] == [1, 2]
    for position, node in enumerate(nodes, start=1):
        assert node["nmt_state"] == "AL PRE-OP" and node["state"] == "SWITCH ON DISABLED"
        assert node["identity"] == {"vendor_id": 0, "product_code": 0x402, "revision": 1,
                                    "serial": position}
        assert {"CST", "CSP", "CSV", "PP", "HM"} <= set(node["modes"])
        assert [(pdo["name"], pdo["mapped"]) for pdo in node["pdos"]] == [
            ("RxPDO 0x1600 (0x1C12:1)", ["0x6040:0 (16 bits)", "0x6071:0 (16 bits)"]),
            ("TxPDO 0x1A00 (0x1C13:1)", ["0x6041:0 (16 bits)", "0x6064:0 (32 bits)"]),
            ("TxPDO 0x1A01 (0x1C13:2)", ["0x606C:0 (32 bits)", "0x6077:0 (16 bits)"])]
        assert node["drivable"]


def test_two_axes_on_one_segment_run_in_one_frame_each_cycle(tmp_path):
    with veth_pair() as veth:
        slave = start_slave(veth, "--node", "1", "--node", "2")
        try:
            out = hil_in(veth, tmp_path, "servo", "run", "--drive",
                         f"ethercat://{veth.master}", "--axes", "x=1,y=2", "--controller",
                         "pid", "--duration", "0.5", "--json",
                         "--out", str(tmp_path / "axes.mcap"))
        finally:
            said = stop_slave(slave)
    assert out.returncode == 0, out.stderr
    assert "would not fit" not in out.stderr  # a CAN bus's plan is no segment's
    over_ethercat = json.loads(out.stdout)
    over_can = api.run_servo("pid", duration_s=0.5, axes="x=1,y=2",
                             out=str(tmp_path / "can.mcap"))
    assert over_ethercat["ticks"] == over_can["ticks"] == 1000
    for axis in ("x", "y"):
        assert {k: over_ethercat["axes"][axis][k] for k in AXIS_KPIS} == \
            {k: over_can["axes"][axis][k] for k in AXIS_KPIS}
    # each frame is a cycle of every slave: one frame a tick, not one an axis
    cycles = int(re.search(r"EtherCAT frames, (\d+) cycles", said)[1])
    assert 1000 <= cycles < 1500, said


def test_a_refused_sdo_is_one_line_with_its_abort_code(tmp_path, capsys):
    with veth_pair() as veth, slave_on(veth):
        out = hil_here_in(veth, tmp_path, capsys, "drive", "sdo", "write",
                          f"ethercat://{veth.master}?slave=1", "0x1000", "5", "--type",
                          "UNSIGNED32")
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        f"hil: error: drive node 1 (EtherCAT slave 1 on ethercat://{veth.master}) refused SDO "
        "write 0x1000:00: 0x06010002 attempt to write a read only object"]


def test_a_fault_mid_run_is_reported_with_its_emergency(tmp_path, capsys):
    with veth_pair() as veth, slave_on(veth, "--clock", "sync", "--fault",
                                       "emcy@0.2:code=0x2310"):
        out = hil_here_in(veth, tmp_path, capsys, "servo", "run", "--drive",
                          f"ethercat://{veth.master}?slave=1", "--controller", "pid",
                          "--duration", "1", "--out", str(tmp_path / "fault.mcap"))
    assert out.returncode == 2
    # the drive in FAULT, or braking towards it (its fault reaction), with the EMCY's code
    assert re.match(r"hil: error: drive node 1 reports FAULT( REACTION ACTIVE)? \(statusword "
                    r"0x02\w\w, last EMCY 0x2310 continuous over-current\)",
                    out.stderr.splitlines()[-1]), out.stderr


@pytest.mark.parametrize("pulled", ["killed", "veth down"])
def test_a_slave_pulled_mid_run_is_a_lost_link(tmp_path, pulled):
    """Lockstep: no frame back within the bound is a gone drive, as on CAN: its state cannot
    be confirmed after (the slave is gone), so the run is unsafe, exit 4, and says so."""
    config = tmp_path / "drive.toml"
    config.write_text(SHORT_LOCKSTEP)
    session = tmp_path / "pulled.mcap"
    with veth_pair() as veth, slave_on(veth) as slave:
        run = popen_hil_in(veth, tmp_path, "servo", "run", "--drive",
                           f"ethercat://{veth.master}?slave=1", "--controller", "pid",
                           "--config", str(config), "--duration", "600", "--out", str(session))
        deadline = time.monotonic() + 120
        while not session.exists() and run.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)  # the session takes its name at the loop's first tick
        assert session.exists(), run.communicate()
        if pulled == "killed":
            slave.kill()
        else:
            veth.set_down(veth.slave)
        _, err = run.communicate(timeout=120)
    assert run.returncode == 4, err
    assert "drive node 1 link lost: no EtherCAT frame came back for 0.5 s" in \
        err.strip().splitlines()[-1]
    assert "hil: unsafe: drive node 1: the link was lost while driving and its state cannot " \
        "be confirmed" in err


def test_the_python_api_drives_over_ethercat_in_this_process(tmp_path):
    with veth_pair() as veth, slave_on(veth), inside(veth):
        kpis = api.run_servo("pid", drive=f"ethercat://{veth.master}?slave=1", duration_s=0.3,
                             out=str(tmp_path / "api.mcap"))
    assert kpis["status"] == "completed" and kpis["ticks"] == 600


USER_TEST = '''
import os

from my_controllers import PdPosition


def test_my_controller_on_the_ethercat_drive(hil_drive):
    kpis = hil_drive.run(PdPosition, {"kp": 300, "kd": 6}, duration_s=0.3,
                         drive_config=os.environ["DRIVE_CONFIG"])
    assert kpis["clock"] == "realtime" and kpis["drive"] == os.environ["DRIVE_URL"]
    assert kpis["status"] in ("completed", "disturbed") and kpis["ticks"] > 0
'''
# a loaded machine's real time: stale cycles counted, not fatal
LOADED_MACHINE = "[master]\nstale_cycles = 100000\nrx_timeout_us = 5000\n" \
    "[safety]\nstale_share_max = 1.0\n"


@pytest.mark.realtime
def test_the_hil_drive_fixture_runs_a_users_test_on_an_ethercat_drive(tmp_path):
    """``pytest --hil-drive ethercat://...``: a user's plain test, in real time, on the
    EtherCAT slave (its lost frames counted as stale cycles)."""
    folder = tmp_path / "my_lab"
    folder.mkdir()
    shutil.copy(REPO / "examples" / "my_controllers.py", folder)
    (folder / "test_on_ethercat.py").write_text(USER_TEST)
    (folder / "drive.toml").write_text(LOADED_MACHINE)
    user_env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    # the drive is enabled in cycles of its own and the loop's first tick follows at once (its
    # real-time set-up done before): within the slave's 100 ms watch on lost cycles (0x2001)
    with veth_pair() as veth, slave_on(veth):
        url = f"ethercat://{veth.master}?slave=1"
        out = subprocess.run(
            veth.command(sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                         "--rootdir", str(folder), "test_on_ethercat.py", "--hil-drive", url),
            cwd=folder, capture_output=True, text=True, timeout=300,
            env={**user_env, "DRIVE_CONFIG": str(folder / "drive.toml"), "DRIVE_URL": url})
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "1 passed" in out.stdout
