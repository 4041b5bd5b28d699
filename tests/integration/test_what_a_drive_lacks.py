"""A drive that lacks objects CiA 402 makes optional, as vendors' drives do (a maxon EPOS4 has
no 0x608F and no 0x6075), driven from the command line: the master reads only what the drive
has, takes the missing scaling from the ``[master]`` keys that stand in for it, stops before
anything is enabled when neither has a value (one line naming the object and the key), and
says on the terminal what it does without the rest. The drive is canopen's ``LocalNode``
(tests/drive_slave.py) built from an EDS file that lacks the objects, or from maxon's own EPOS4
DCF, over python-can's ``virtual`` bus in this process (``hil_here``) and over
``udp_multicast`` from another one."""

import json
import math
import os
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import canopen
import pytest

from hil.core.recording.reader import read_session
from tests.cli import hil_here
from tests.drive_slave import CSP, CST, INCREMENTS, PP, RATED_MA, dictionary, serve
from tests.integration.test_independent_drive import free_udp_port

pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
NODE = 3
EPOS4_LACKS = (0x608F, 0x6075)
STAND_INS = f"[master]\nincrements_per_rev = {INCREMENTS}\nrated_current_mA = {RATED_MA}\n"


@pytest.fixture(autouse=True)
def quick_disconnect(monkeypatch):
    """canopen's notifiers poll the bus every 0.1 s, not 1 s: a slave's disconnect waits out
    one poll."""
    monkeypatch.setattr(canopen.Network, "NOTIFIER_CYCLE", 0.1)


def lacking_eds(tmp_path, without, modes=(CST,), name="drive"):
    """An EDS of the independent drive without the objects ``without``."""
    path = tmp_path / f"{name}.eds"
    canopen.export_od(dictionary(NODE, without=without, modes=modes), str(path), doc_type="eds")
    return path


class Slave:
    """The independent drive built from the EDS at ``eds``, on a virtual bus of its own."""

    def __init__(self, eds):
        self.url = f"virtual://lacks-{uuid.uuid4().hex}"
        self.network, self.drive = serve(self.url, NODE, od=canopen.import_od(str(eds), NODE))

    def written(self, index):
        return [w for w in self.drive.writes if w[0] == index]

    def close(self):
        self.network.disconnect()


@pytest.fixture
def slave_of(tmp_path):
    slaves = []

    def start(without, modes=(CST,)):
        slaves.append(Slave(lacking_eds(tmp_path, without, modes, f"drive{len(slaves)}")))
        return slaves[-1]

    yield start
    for slave in slaves:
        slave.close()


def run(capsys, tmp_path, slave, config="", *extra, name="run", controller="pid"):
    (tmp_path / f"{name}.toml").write_text(config)
    return hil_here(capsys, "servo", "run", "--controller", controller, "--drive", slave.url,
                    "--node", NODE, "--duration", "0.1", "--config", f"{name}.toml",
                    "--out", f"{name}.mcap", *extra, cwd=tmp_path)


def test_a_drive_without_0x608f_and_0x6075_stops_before_anything_is_enabled(tmp_path, capsys,
                                                                            slave_of):
    slave = slave_of(EPOS4_LACKS)
    refused = run(capsys, tmp_path, slave)
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines()[-1] == (
        "hil: error: drive node 3 has no 0x608F:1 (encoder increments per motor revolution): "
        "set [master] increments_per_rev to its value")
    assert not (tmp_path / "run.mcap").exists()
    assert slave.drive.state == "SWITCH ON DISABLED" and slave.drive.syncs == 0
    assert slave.written(0x6040) == [] and slave.written(0x6060) == []  # nothing configured
    (tmp_path / "half.toml").write_text(f"[master]\nincrements_per_rev = {INCREMENTS}\n")
    half = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive", slave.url,
                    "--node", NODE, "--config", "half.toml", "--out", "half.mcap",
                    cwd=tmp_path)
    assert half.returncode == 2 and half.stderr.strip().endswith(
        "drive node 3 has no 0x6075 (rated current [mA], what the torque objects are per mille "
        "of): set [master] rated_current_mA to its value")


@pytest.mark.parametrize("mode, controller", [("cst", "pid"), ("csp", "setpoint")])
def test_the_keys_that_stand_in_for_them_drive_it_and_are_recorded(tmp_path, capsys, slave_of,
                                                                   mode, controller):
    slave = slave_of(EPOS4_LACKS, (CSP, CST))
    ran = run(capsys, tmp_path, slave, STAND_INS + f'mode = "{mode}"\n', "--json",
              controller=controller)
    assert ran.returncode == 0, ran.stderr
    kpis = json.loads(ran.stdout)
    assert kpis["ticks"] == 200 and kpis["stale_feedback"] == 0
    assert kpis["rms_error_deg"] < 1.0  # scaled right: it tracks the sine
    # driven in the mode, the drive's own put back after the run
    assert slave.drive.written(0x6060)[0] == {"cst": CST, "csp": CSP}[mode]
    assert slave.drive.value(0x6060) == slave.drive.written(0x6060)[-1] == 0
    session = read_session(str(tmp_path / "run.mcap"))
    drive = json.loads(session.metadata["drive"]["json"])
    assert drive["scaling"]["increments_per_rev"] == INCREMENTS
    assert drive["scaling_from"] == {"increments_per_rev": "[master] increments_per_rev",
                                     "rated_current_ma": "[master] rated_current_mA"}
    settings = json.loads(session.metadata["config"]["json"])["settings"]
    assert settings["master.increments_per_rev"] == {"value": INCREMENTS,
                                                     "origin": "--config run.toml"}
    [stand_in] = [m for _, m in session.topic("/events") if m["kind"] == "drive.stand_in"]
    assert "[master] increments_per_rev" in stand_in["message"]
    # the objects it lacks were neither read nor written; those it has, read
    assert slave.written(0x608F) == slave.written(0x6075) == []


@pytest.mark.parametrize("mode, command", [("cst", "pid"), ("csp", "setpoint"), ("pp", None)])
def test_a_drive_without_0x6077_is_driven_and_its_current_is_not_measured(
        tmp_path, capsys, slave_of, mode, command):
    """ros2_canopen's CiA 402 test device has no torque actual value: on main every mode
    failed configuring its TPDOs (abort 0x06020000 on 0x1A01:2 = 0x6077). Its TPDOs now carry
    what it has; the current is NaN on /drive/feedback, the peak current the commanded one
    (CST) or none."""
    slave = slave_of((0x6077,), (CSP, CST, PP))
    config = f'[master]\nmode = "{mode}"\n'
    if command is None:
        (tmp_path / "pp.toml").write_text(config)
        ran = hil_here(capsys, "drive", "move", slave.url, "10", "--node", NODE, "--config",
                       "pp.toml", "--json", "--out", "run.mcap", cwd=tmp_path)
    else:
        ran = run(capsys, tmp_path, slave, config, "--json", controller=command)
    assert ran.returncode == 0, ran.stderr
    assert ("hil: warning: drive node 3 has no 0x6077 (torque actual value): its current is "
            "not measured: /drive/feedback has current_mA NaN") in ran.stderr
    kpis = json.loads(ran.stdout)
    if command is None:
        assert kpis["reached"] and kpis["position_deg"] == pytest.approx(10.0, abs=0.1)
    else:
        assert kpis["ticks"] == 200 and kpis["rms_error_deg"] < 1.0
    assert (kpis["peak_current_mA"] > 0) if mode == "cst" else kpis["peak_current_mA"] is None
    mapped = {int.from_bytes(data, "little") >> 16 for index, sub, data in slave.written(0x1A01)
              if sub > 0}
    assert mapped == {0x606C}  # TPDO2: the velocity alone
    currents = read_session(str(tmp_path / "run.mcap")).arrays("/drive/feedback")["current_mA"]
    assert len(currents) > 0 and all(math.isnan(current) for current in currents)


def test_a_key_that_disagrees_with_the_drive_is_refused(tmp_path, capsys, slave_of):
    slave = slave_of(())
    refused = run(capsys, tmp_path, slave, "[master]\nincrements_per_rev = 4096\n")
    assert refused.returncode == 2
    assert refused.stderr.strip().endswith(
        "drive node 3: [master] increments_per_rev = 4096 stands in for 0x608F:1 (encoder "
        f"increments per motor revolution) on a drive without it, and this drive has it: "
        f"{INCREMENTS}; drop the key")


def test_a_drive_without_0x6072_is_not_written_and_the_run_says_the_clamp_is_the_limit(
        tmp_path, capsys, slave_of):
    slave = slave_of((0x6072,))
    ran = run(capsys, tmp_path, slave, "", "--umax", "300")
    assert ran.returncode == 0, ran.stderr
    assert ("hil: warning: drive node 3 has no 0x6072 (max torque): the run's limit of 300 mA "
            "cannot be given to the drive; hil's clamp (300 mA) is the only limit of the "
            "current") in ran.stderr
    assert slave.written(0x6072) == []


def test_a_drive_without_the_optional_settings_runs_and_says_what_it_does_without(
        tmp_path, capsys, slave_of):
    """Lacking in its EDS, or refused by SDO abort 0x06020000 (0x1017: canopen's LocalNode
    needs it for its own heartbeat, so its file keeps it)."""
    slave = slave_of((0x605A, 0x1006, 0x1016, 0x603F, 0x6502))
    slave.drive.refuses = (0x1017,)
    ran = run(capsys, tmp_path, slave)
    assert ran.returncode == 0, ran.stderr
    warnings = [line for line in ran.stderr.splitlines() if line.startswith("hil: warning:")]
    for told in ("has no 0x6502 (supported drive modes): the mode is checked by 0x6061 alone",
                 "has no 0x1006 (communication cycle period): the drive is not told the SYNC "
                 "period",
                 "has no 0x1017 (producer heartbeat time): the master watches the drive's "
                 "TPDOs alone, not a heartbeat",
                 "has no 0x1016:1 (consumer heartbeat time): the drive does not watch the "
                 "master's heartbeat",
                 "has no 0x605A (quick stop option code): its own quick stop applies, not "
                 "[master] quick_stop_option"):
        assert any(told in line for line in warnings), told
    for index in (0x605A, 0x1006, 0x1016, 0x1017):
        assert slave.written(index) == []
    events = [m for _, m in read_session(str(tmp_path / "run.mcap")).topic("/events")
              if m["kind"] == "drive.object_missing"]
    assert len(events) == 5


def test_from_outside_a_drive_built_from_a_file_without_them(tmp_path):
    """The drive in another process, its dictionary the EDS's, reached over udp_multicast,
    in CSP."""
    eds = lacking_eds(tmp_path, EPOS4_LACKS, (CSP, CST))
    url = f"udp_multicast://239.0.0.1?port={free_udp_port()}"
    log = tmp_path / "slave.json"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    slave = subprocess.Popen([sys.executable, str(ROOT / "tests" / "drive_slave.py"), url,
                              str(NODE), str(log), "--eds", str(eds)], stdout=subprocess.PIPE,
                             text=True, env=env)
    (tmp_path / "drive.toml").write_text(STAND_INS + 'mode = "csp"\n')
    try:
        assert slave.stdout.readline().strip() == "serving"
        ran = subprocess.run([sys.executable, "-m", "hil", "servo", "run", "--controller",
                              "setpoint", "--drive", url, "--node", str(NODE), "--config",
                              "drive.toml", "--eds", str(eds), "--duration", "0.2", "--json",
                              "--out", "run.mcap"], cwd=tmp_path, env=env,
                             capture_output=True, text=True, timeout=120)
    finally:
        slave.send_signal(signal.SIGTERM)
        slave.wait(timeout=10)
    assert ran.returncode == 0, ran.stderr
    kpis = json.loads(ran.stdout)
    assert kpis["ticks"] == 400 and kpis["stale_feedback"] == 0
    assert kpis["set_point"] == "position" and kpis["rms_error_deg"] < 1.0


def ip_only(tmp_path):
    """The EDS of a drive whose 0x6502 lists interpolated position (IP) alone."""
    od = dictionary(NODE)
    od[0x6502].default = 0x40
    path = tmp_path / "ip-only.eds"
    canopen.export_od(od, str(path), doc_type="eds")
    return path


def test_scan_with_an_eds_lists_one_problem_a_line_and_fails(tmp_path, capsys, slave_of):
    slave = slave_of((0x606C,), (CSP, CST))  # no velocity actual: hil cannot drive it
    eds = lacking_eds(tmp_path, (0x606C,), (CSP, CST), "described")
    (tmp_path / "csp.toml").write_text('[master]\nmode = "csp"\n')
    scanned = hil_here(capsys, "drive", "scan", slave.url, "--node", NODE, "--eds", eds,
                       "--config", "csp.toml", cwd=tmp_path)
    assert scanned.returncode == 1, scanned.stderr
    verdict = scanned.stdout[scanned.stdout.index("can drive: no"):].splitlines()
    assert verdict == [
        "can drive: no, 0x606C velocity actual: drive node 3 refused SDO read 0x606C:00: "
        "0x06020000 object does not exist in the object dictionary",
        f"    EDS {eds}: 0x606C is not in it: hil needs it readable and TPDO-mappable, 32 "
        "bits, for the velocity every cycle"]
    healthy = slave_of((), (CSP, CST))
    fine = hil_here(capsys, "drive", "scan", healthy.url, "--node", NODE, "--eds",
                    lacking_eds(tmp_path, (), (CSP, CST), "complete"), "--config", "csp.toml",
                    cwd=tmp_path)
    assert fine.returncode == 0, fine.stdout
    assert "can drive: yes, in CSP" in fine.stdout


def test_a_drive_with_no_mode_hil_drives_says_that_first(tmp_path, capsys):
    eds = ip_only(tmp_path)
    slave = Slave(eds)
    try:
        scanned = hil_here(capsys, "drive", "scan", slave.url, "--node", NODE, "--eds", eds,
                           cwd=tmp_path)
        ran = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive", slave.url,
                       "--node", NODE, "--eds", eds, "--out", "x.mcap", cwd=tmp_path)
    finally:
        slave.close()
    assert scanned.returncode == 1
    modes = ("supports no mode hil drives (IP: 0x6502 = 0x00000040; hil drives PP, PV, HM, "
             "CSP, CSV, CST)")
    assert f"can drive: no, {modes}" in scanned.stdout
    assert ran.returncode == 2 and ran.stderr.startswith(
        f"hil: error: drive node 3 (EDS {eds}): {modes}")
    assert not (tmp_path / "x.mcap").exists()


def test_scan_with_an_epos4_like_file_drives_it_with_the_stand_ins(tmp_path, capsys, slave_of):
    """On main every object the master read was needed: the scan of a file without 0x608F
    and 0x6075 said it could not drive the drive whatever the config."""
    slave = slave_of(EPOS4_LACKS, (CSP, CST))
    eds = lacking_eds(tmp_path, EPOS4_LACKS, (CSP, CST), "epos4-like")
    bare = hil_here(capsys, "drive", "scan", slave.url, "--node", NODE, "--eds", eds,
                    cwd=tmp_path)
    assert bare.returncode == 1
    assert ("can drive: no, its position and current cannot be scaled: has no 0x608F:1 "
            "(encoder increments per motor revolution): set [master] increments_per_rev to "
            "its value") in bare.stdout
    (tmp_path / "stand-ins.toml").write_text(STAND_INS + 'mode = "csp"\n')
    scanned = hil_here(capsys, "drive", "scan", slave.url, "--node", NODE, "--eds", eds,
                       "--config", "stand-ins.toml", "--json", cwd=tmp_path)
    assert scanned.returncode == 0, scanned.stdout
    [node] = json.loads(scanned.stdout)["nodes"]
    assert node["verdict"] == "can drive: yes, in CSP" and node["eds"]["problems"] == []
    assert node["scaling_from"]["increments_per_rev"] == "[master] increments_per_rev"


EPOS4 = ROOT / "tests" / "data" / "drives" / "maxon" / \
    "epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf"


def epos4_config(folder, mode, stand_ins=True):
    """maxon's own DCF of an EPOS4 as the master's description and the emulator's twin (its
    commissioning values supplied: 4096 increments, 2 A), with or without the stand-ins."""
    keys = "increments_per_rev = 4096\nrated_current_mA = 2000.0\n" if stand_ins else ""
    path = folder / f"epos4-{mode}-{stand_ins}.toml"
    path.write_text(f'[master]\nmode = "{mode}"\neds = "{EPOS4}"\n{keys}'
                    f'[emulator]\neds = "{EPOS4}"\n'
                    'set = {"0x608F:1" = 4096, "0x608F:2" = 1, "0x6075:0" = 2000}\n')
    return path.name


@pytest.mark.parametrize("mode, controller", [("cst", "pid"), ("csp", "setpoint"),
                                              ("csv", "setpoint")])
def test_a_maxon_epos4_is_driven_with_the_stand_ins(tmp_path, capsys, mode, controller):
    """The vendor's file lacks 0x608F, 0x6075, 0x6072 and 0x1006: nothing of them is read or
    written, the stand-ins give the scaling, the terminal says what hil does without."""
    refused = hil_here(capsys, "servo", "run", "--controller", controller, "--config",
                       epos4_config(tmp_path, mode, stand_ins=False), "--out", "x.mcap",
                       cwd=tmp_path)
    assert refused.returncode == 2 and refused.stderr.strip().splitlines()[-1].endswith(
        "set [master] increments_per_rev to its value")
    ran = hil_here(capsys, "servo", "run", "--controller", controller, "--config",
                   epos4_config(tmp_path, mode), "--duration", "0.5", "--json", "--out",
                   "run.mcap", cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr
    kpis = json.loads(ran.stdout)
    assert kpis["ticks"] == 1000 and kpis["stale_feedback"] == 0
    assert kpis["rms_error_deg"] < 1.0
    assert "drive node 1 has no 0x6072 (max torque)" in ran.stderr
    assert "drive node 1 has no 0x1006 (communication cycle period)" in ran.stderr


def test_a_maxon_epos4_homes_and_moves(tmp_path, capsys):
    config = epos4_config(tmp_path, "pp")
    homed = hil_here(capsys, "drive", "home", "emulated", "--config", config, "--method", "37",
                     "--json", "--out", "home.mcap", cwd=tmp_path)
    moved = hil_here(capsys, "drive", "move", "emulated", "45", "--config", config,
                     "--velocity", "90", "--acceleration", "720", "--deceleration", "720",
                     "--json", "--out", "move.mcap", cwd=tmp_path)
    assert homed.returncode == 0, homed.stderr
    assert moved.returncode == 0, moved.stderr
    assert json.loads(homed.stdout)["reached"]
    kpis = json.loads(moved.stdout)
    assert kpis["reached"] and kpis["position_deg"] == pytest.approx(45.0, abs=0.5)


@pytest.mark.parametrize("mode, controller", [("cst", "pid"), ("csp", "setpoint")])
def test_a_drive_built_from_maxons_own_dcf_is_driven_with_the_stand_ins(tmp_path, capsys, mode,
                                                                        controller):
    """canopen's LocalNode with the dictionary of maxon's EPOS4 DCF (no 0x608F, no 0x6075, no
    0x6072, no 0x1006; its PDOs valid at power-on, mapped otherwise): a drive hil did not
    write, as its vendor describes it, that DCF the run's --eds too. Its scaling comes from the
    stand-ins; nothing it lacks is read or written."""
    slave = Slave(EPOS4)
    try:
        assert not {0x608F, 0x6075} & set(slave.drive.od.keys())
        ran = run(capsys, tmp_path, slave, STAND_INS + f'mode = "{mode}"\n', "--eds", EPOS4,
                  "--json", controller=controller)
    finally:
        slave.close()
    assert ran.returncode == 0, ran.stderr
    kpis = json.loads(ran.stdout)
    assert kpis["ticks"] == 200 and kpis["stale_feedback"] == 0
    assert kpis["rms_error_deg"] < 1.0  # scaled right: it tracks the sine
    # the run's mode was written, then the drive's own put back when the run let it go
    assert slave.drive.written(0x6060) == [{"cst": CST, "csp": CSP}[mode], 1]
    assert slave.drive.value(0x6060) == 1
    assert slave.written(0x608F) == slave.written(0x6075) == slave.written(0x6072) == []
    assert "drive node 3 has no 0x6072 (max torque)" in ran.stderr
    drive = json.loads(read_session(str(tmp_path / "run.mcap")).metadata["drive"]["json"])
    assert drive["scaling_from"] == {"increments_per_rev": "[master] increments_per_rev",
                                     "rated_current_ma": "[master] rated_current_mA"}
    assert drive["eds"]["vendor"].startswith("maxon")
