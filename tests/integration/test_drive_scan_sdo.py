"""``hil drive scan`` and ``hil drive sdo`` run as a user runs them (a subprocess, outside the
repository), against hil's emulator (a fault injected, an axis moved by a run) and against a
drive hil did not write (tests/drive_slave.py: canopen's LocalNode, 17-bit encoder, 2 A rated,
CST only) on ``udp_multicast`` from this process; and ``hil emulate drive --write-eds``'s file
read back by canopen at two node ids, against the emulator serving at the second. The emulator
serves in this process (:func:`tests.served_here.drive_served_here`: a process start is
some 0.45 s of CPU).

Each command and flag runs from outside at least once; its other cases run ``main`` in this
process (``hil_here``: the same exit status and output, without a second of interpreter start)."""

import configparser
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import canopen
import pytest

from hil import api
from hil.core.device_lock import LOCK_DIR_ENV, lock_device
from hil.core.recording.reader import read_session
from hil.emulators.drive.eds import BIT_RATES
from tests.cli import hil_here as in_process
from tests.drive_slave import INCREMENTS, RATED_MA, dictionary, serve
from tests.served_here import drive_served_here

pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
NODE = 3


def hil(*args, cwd):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "hil", *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def hil_here(*args, cwd, capsys):
    """``hil ARGS`` run by ``main`` in this process, as :func:`hil` reports it."""
    return in_process(capsys, *args, cwd=cwd)


def one_error_line(result):
    """The one ``hil: error:`` line of a run that failed with exit status 2."""
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr
    [line] = result.stderr.strip().splitlines()
    assert line.startswith("hil: error: ")
    return line


def free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture
def slave(monkeypatch):
    """The independent drive as node 3 on a udp_multicast bus of its own; yields (url, slave).
    Its network's notifier polls the bus every 0.1 s, not canopen's 1 s: disconnecting waits
    out one poll."""
    monkeypatch.setattr(canopen.Network, "NOTIFIER_CYCLE", 0.1)
    url = f"udp_multicast://239.0.0.1?port={free_udp_port()}"
    network, node = serve(url, NODE)
    try:
        yield url, node
    finally:
        network.disconnect()


def slave_eds(tmp_path, change=None, name="slave"):
    """The independent drive's own dictionary as an EDS (``change`` applied to it first)."""
    od = dictionary(NODE)
    if change:
        change(od)
    path = tmp_path / f"{name}.eds"
    canopen.export_od(od, str(path), doc_type="eds")
    return path


def wait_for_fault(emulator, timeout_s=30.0):
    deadline = time.monotonic() + timeout_s
    while not emulator.fault_events():
        assert time.monotonic() < deadline, "the emulator never injected its fault"
        time.sleep(0.05)


# -- scan -----------------------------------------------------------------------------------
def test_scan_of_a_faulted_drive_says_it_cannot_drive_it_and_names_the_fault(tmp_path, capsys):
    with drive_served_here(faults=["emcy@0:code=0x8130"]) as emulator:
        wait_for_fault(emulator)
        table = hil("drive", "scan", emulator.url, cwd=tmp_path)
        faulted = hil_here("drive", "scan", emulator.url, "--json", cwd=tmp_path, capsys=capsys)
        assert hil_here("drive", "reset", emulator.url, cwd=tmp_path,
                        capsys=capsys).returncode == 0
        cleared = hil_here("drive", "scan", emulator.url, "--json", cwd=tmp_path, capsys=capsys)
    assert table.returncode == 0, table.stderr
    assert "CiA 402 state FAULT (statusword 0x" in table.stdout
    assert "error code 0x8130 heartbeat or life guard error" in table.stdout
    assert ("can drive: no, in FAULT (0x8130 heartbeat or life guard error), `hil drive reset` "
            "clears it") in table.stdout
    assert "can drive: yes" not in table.stdout
    [node] = json.loads(faulted.stdout)["nodes"]
    assert node["state"] == "FAULT" and node["error_code"] == 0x8130
    assert node["drivable"] is False and node["verdict"].startswith("can drive: no, in FAULT")
    [node] = json.loads(cleared.stdout)["nodes"]
    assert node["state"] == "SWITCH ON DISABLED" and node["drivable"] is True
    assert node["verdict"] == "can drive: yes, in CST"


def test_scan_of_a_healthy_drive_names_its_modes_and_where_the_axis_stands(tmp_path, capsys):
    with drive_served_here() as emulator:
        api.run_servo("pid", drive=emulator.url, duration_s=0.5,
                      reference="hold:position=40", out=str(tmp_path / "hold.mcap"))
        table = hil_here("drive", "scan", emulator.url, cwd=tmp_path, capsys=capsys)
        report = hil_here("drive", "scan", emulator.url, "--json", cwd=tmp_path, capsys=capsys)
    last = [m for _, m in read_session(str(tmp_path / "hold.mcap")).topic("/drive/feedback")][-1]
    [node] = json.loads(report.stdout)["nodes"]
    assert node["modes"] == ["PP", "PV", "HM", "CSP", "CSV", "CST"]
    assert node["supported_modes"] == 0x3A5
    assert "supported modes PP, PV, HM, CSP, CSV, CST (0x6502 = 0x000003A5)" in table.stdout
    assert node["scaling"]["counts_per_turn"] == 1 << 20
    assert node["position_deg"] == pytest.approx(node["position_counts"] * 360 / (1 << 20))
    assert node["position_deg"] == pytest.approx(last["position_deg"], abs=1.0)  # the stop
    assert f"position {node['position_deg']:.3f} deg" in table.stdout
    assert node["state"] == "SWITCH ON DISABLED" and node["error_text"] == "none"
    assert "can drive: yes, in CST" in table.stdout


def test_scan_of_a_drive_hil_did_not_write_scales_by_its_own_encoder(tmp_path, slave, capsys):
    url, drive = slave
    drive.position = 123.4  # degrees: 0x6064 counts of its 17-bit encoder
    report = hil_here("drive", "scan", url, "--node", NODE, "--json", cwd=tmp_path,
                      capsys=capsys)
    config = tmp_path / "csp.toml"
    config.write_text('[master]\nmode = "csp"\n')
    csp = hil("drive", "scan", url, "--node", NODE, "--config", config, cwd=tmp_path)
    assert report.returncode == 0, report.stderr
    [node] = json.loads(report.stdout)["nodes"]
    assert node["node_id"] == NODE and node["position_counts"] == round(123.4 / 360 * INCREMENTS)
    assert node["position_deg"] == pytest.approx(123.4, abs=360 / INCREMENTS)
    assert node["scaling"]["increments_per_rev"] == INCREMENTS
    assert node["scaling"]["rated_current_ma"] == RATED_MA
    assert node["modes"] == ["CST"] and node["drivable"] is True
    assert "can drive: no, mode CSP not supported (it supports CST: 0x6502 = 0x00000200)" \
        in csp.stdout


def test_scan_with_an_eds_that_lacks_an_object_hil_needs_reports_it(tmp_path, slave, capsys):
    url, _drive = slave

    def drop_velocity_actual(od):
        del od[0x606C]

    def here(*args):
        return hil_here(*args, cwd=tmp_path, capsys=capsys)

    complete = here("drive", "scan", url, "--node", NODE, "--eds", slave_eds(tmp_path), "--json")
    lacking = slave_eds(tmp_path, drop_velocity_actual, "lacking")
    table = hil("drive", "scan", url, "--node", NODE, "--eds", lacking, cwd=tmp_path)
    report = here("drive", "scan", url, "--node", NODE, "--eds", lacking, "--json")
    emulators = tmp_path / "emulator.eds"
    assert here("emulate", "drive", "--write-eds", emulators).returncode == 0
    other = here("drive", "scan", url, "--node", NODE, "--eds", emulators, "--json")
    missing = here("drive", "scan", url, "--eds", tmp_path / "none.eds")
    [node] = json.loads(complete.stdout)["nodes"]
    assert node["eds"]["problems"] == [] and node["drivable"] is True
    [node] = json.loads(report.stdout)["nodes"]
    [problem] = node["eds"]["problems"]
    assert problem.startswith("0x606C is not in it: hil needs it readable and TPDO-mappable")
    assert node["drivable"] is False
    assert f"EDS {lacking}: 1 problem(s), below" in table.stdout
    assert f"can drive: no, EDS {lacking}: 0x606C is not in it" in table.stdout
    [node] = json.loads(other.stdout)["nodes"]  # hil's emulator's EDS: another product
    assert "is for vendor id 0x0, the drive says 0xC0FFEE (0x1018)" in node["eds"]["problems"]
    assert "cannot read its EDS" in one_error_line(missing)


def test_scan_reads_an_eds_that_is_not_utf8(tmp_path, slave, capsys):
    """FAULHABER's EDS has a Windows-1252 byte in a comment: the twin read it, and the scan,
    a run's --eds and hil drive sdo said "cannot read its EDS" ('utf-8' codec can't decode)."""
    url, _drive = slave
    path = slave_eds(tmp_path, name="cp1252")
    text = path.read_bytes().replace(b"[FileInfo]\n", b"[FileInfo]\n; \x94quoted\x94\n", 1)
    path.write_bytes(text)
    with pytest.raises(UnicodeDecodeError):
        text.decode("utf-8")
    scanned = hil_here("drive", "scan", url, "--node", NODE, "--eds", path, "--json",
                       cwd=tmp_path, capsys=capsys)
    assert scanned.returncode == 0, scanned.stdout + scanned.stderr
    [node] = json.loads(scanned.stdout)["nodes"]
    assert node["eds"]["problems"] == [] and node["drivable"] is True


# -- sdo ------------------------------------------------------------------------------------
def test_sdo_write_then_read_round_trip_on_a_drive_hil_did_not_write(tmp_path, slave, capsys):
    url, drive = slave
    eds = slave_eds(tmp_path)
    written = hil("drive", "sdo", "write", url, "0x6072", "777", "--node", NODE, "--eds", eds,
                  cwd=tmp_path)
    typed = hil("drive", "sdo", "read", url, "0x6072", "--node", NODE, "--eds", eds, "--json",
                cwd=tmp_path)
    raw = hil_here("drive", "sdo", "read", url, "6072:0", "--node", NODE, cwd=tmp_path,
                   capsys=capsys)
    signed = hil_here("drive", "sdo", "write", url, "0x605A", "-1", "--node", NODE, "--type",
                      "INTEGER16", cwd=tmp_path, capsys=capsys)
    name = hil_here("drive", "sdo", "read", url, "0x1008", "--node", NODE, "--type", "str",
                    cwd=tmp_path, capsys=capsys)
    assert written.returncode == 0, written.stderr
    assert written.stdout.strip() == "node 3 0x6072:0 UNSIGNED16 = 777: written"
    assert drive.value(0x6072) == 777  # the slave holds it
    assert json.loads(typed.stdout) == {"node": 3, "object": "0x6072:0", "index": 0x6072,
                                        "subindex": 0, "type": "UNSIGNED16", "size": 2,
                                        "hex": "0903", "value": 777}
    assert raw.stdout.strip() == "node 3 0x6072:0 = 09 03 (2 bytes, unsigned 777)"
    assert signed.returncode == 0 and drive.value(0x605A) == -1
    assert name.stdout.strip() == "node 3 0x1008:0 VISIBLE_STRING = 'independent 402 slave'"


def test_a_write_to_a_pdo_mapped_object_of_an_operational_drive_is_refused(tmp_path, slave,
                                                                           capsys):
    url, drive = slave
    eds = slave_eds(tmp_path)

    def here(*args):
        return hil_here(*args, cwd=tmp_path, capsys=capsys)

    assert here("drive", "sdo", "write", url, "0x1017", "200", "--node", NODE, "--eds",
                eds).returncode == 0  # its heartbeat on: the NMT state is heard
    drive.node.nmt.state = "OPERATIONAL"
    by_heartbeat = hil("drive", "sdo", "write", url, "0x6071", "100", "--node", NODE,
                       "--type", "i16", cwd=tmp_path)
    unmapped = here("drive", "sdo", "write", url, "0x6072", "500", "--node", NODE,
                    "--type", "u16")
    assert here("drive", "sdo", "write", url, "0x1017", "0", "--node", NODE, "--type",
                "u16").returncode == 0  # no heartbeat now: the statusword says it
    drive.node.nmt.state = "PRE-OPERATIONAL"
    drive.state = "OPERATION ENABLED"
    by_statusword = here("drive", "sdo", "write", url, "0x6040", "0x0F", "--node", NODE,
                         "--eds", eds)
    enabled = here("drive", "scan", url, "--node", NODE, "--json")
    drive.state = "SWITCH ON DISABLED"
    allowed = here("drive", "sdo", "write", url, "0x6071", "100", "--node", NODE,
                   "--type", "i16")
    line = one_error_line(by_heartbeat)
    assert "not written: 0x6071:0 is mapped in RPDO1 and the drive is NMT OPERATIONAL (its " \
        "heartbeat)" in line
    assert unmapped.returncode == 0 and drive.value(0x6072) == 500
    line = one_error_line(by_statusword)
    assert "0x6040:0 is mapped in RPDO1 and the drive is OPERATION ENABLED (0x6041 = 0x" in line
    assert allowed.returncode == 0 and drive.value(0x6071) == 100  # not operational: written
    [node] = json.loads(enabled.stdout)["nodes"]  # a run would take it over: said, not refused
    assert node["state"] == "OPERATION ENABLED" and node["drivable"] is True
    assert node["verdict"] == ("can drive: yes, in CST; it is in OPERATION ENABLED now "
                               "(another master?): a run disables voltage first")


def test_sdo_aborts_and_bad_input_are_one_line(tmp_path, slave, capsys):
    url, _drive = slave

    def here(*args):
        return hil_here(*args, cwd=tmp_path, capsys=capsys)

    no_object = here("drive", "sdo", "read", url, "0x2222", "--node", NODE)
    read_only = here("drive", "sdo", "write", url, "0x6041", "1", "--node", NODE, "--type",
                     "u16")
    too_big = here("drive", "sdo", "write", url, "0x6072", "70000", "--node", NODE, "--type",
                   "u16")
    wrong_size = hil("drive", "sdo", "read", url, "0x6064", "--node", NODE, "--type", "u16",
                     cwd=tmp_path)
    untyped = here("drive", "sdo", "write", url, "0x6072", "1", "--node", NODE)
    bad_type = here("drive", "sdo", "read", url, "0x6072", "--type", "u12")
    bad_object = here("drive", "sdo", "read", url, "0x6072:x")
    assert one_error_line(no_object).endswith(
        "drive node 3 refused SDO read 0x2222:00: 0x06020000 object does not exist in the "
        "object dictionary")
    assert "0x06010002 attempt to write a read only object" in one_error_line(read_only)
    assert "VALUE '70000' is not a valid UNSIGNED16 (0..65535)" in one_error_line(too_big)
    assert "0x6064:0 has 4 bytes (00 00 00 00), UNSIGNED16 is 2" in one_error_line(wrong_size)
    assert "needs the object's type: --type T or --eds F.eds" in one_error_line(untyped)
    assert "unknown type 'u12'" in bad_type.stderr and bad_type.returncode == 2
    assert "expected INDEX[:SUB]" in bad_object.stderr and bad_object.returncode == 2


def test_sdo_takes_the_bus_lock_as_scan_does(tmp_path, slave, monkeypatch, capsys):
    url, _drive = slave
    monkeypatch.setenv(LOCK_DIR_ENV, str(tmp_path / "locks"))
    with lock_device(url, "drive bus"):
        held = hil("drive", "sdo", "read", url, "0x6041", "--node", NODE, cwd=tmp_path)
    free = hil_here("drive", "sdo", "read", url, "0x6041", "--node", NODE, cwd=tmp_path,
                    capsys=capsys)
    assert f"drive bus {url} is in use by another hil run (pid {os.getpid()})" in \
        one_error_line(held)
    assert free.returncode == 0, free.stderr


# -- the emulator's EDS ----------------------------------------------------------------------
def test_the_written_eds_gives_every_node_its_own_cob_ids_and_claims_the_bit_rates(tmp_path,
                                                                                  capsys):
    eds = tmp_path / "drive.eds"
    assert hil("emulate", "drive", "--write-eds", eds, cwd=tmp_path).returncode == 0
    cob_ids = {}
    for node in (1, 5):
        od = canopen.import_od(str(eds), node)
        cob_ids[node] = (od[0x1800][1].default & 0x7FF, od[0x1400][1].default,
                         od[0x1014].default, od[0x1200][1].default, od[0x1200][2].default)
        assert od.device_information.allowed_baudrates == set(BIT_RATES)
    assert cob_ids == {1: (0x181, 0x201, 0x81, 0x601, 0x581),
                       5: (0x185, 0x205, 0x85, 0x605, 0x585)}
    text = configparser.ConfigParser()
    text.read(eds)
    assert text["1800sub1"]["DefaultValue"] == "$NODEID+0x40000180"
    assert text["1014"]["DefaultValue"] == "$NODEID+0x80"
    rates = {k: v for k, v in text["DeviceInfo"].items() if k.lower().startswith("baudrate_")}
    assert rates == {f"baudrate_{r // 1000}": "1" for r in BIT_RATES}
    # what the file says of node 5 is what the emulator serving node 5 answers
    od5 = canopen.import_od(str(eds), 5)
    with drive_served_here(node=5) as emulator:
        for index, sub in ((0x1014, 0), (0x1200, 1), (0x1200, 2), (0x1400, 1), (0x1800, 1),
                           (0x1801, 1), (0x1018, 4)):
            read = hil_here("drive", "sdo", "read", emulator.url, f"0x{index:04X}:{sub}",
                            "--node", 5, "--eds", eds, "--json", cwd=tmp_path, capsys=capsys)
            assert read.returncode == 0, read.stderr
            expected = od5.get_variable(index, sub).default
            value = json.loads(read.stdout)["value"]
            if (index, sub) == (0x1018, 4):  # a serial of the emulator process's own: the
                value &= 0x7F                # node id in its low 7 bits, as the file's is
            assert value == expected, (hex(index), sub)
