"""The drive side's tools, from outside as a user runs them: ``hil drive scan`` against the
emulator and against a drive hil did not write, ``hil drive reset`` and ``--reset-fault``,
the drive's EDS checked before anything is enabled, ``--can-log`` files python-can reads
back, and the emulator's late TPDOs in real time bound to their SYNC through the wire trace.
Each command and flag runs from outside at least once; its other cases run ``main`` in this
process (``hil_here``: the same exit status and output, without a second of interpreter start).
The emulator serves in this process (:func:`tests.served_here.drive_served_here`) but where
it runs in real time, as a process of its own."""

import json
import os
import re
import struct
import subprocess
import sys
import uuid
from pathlib import Path

import can
import canopen
import pytest

from hil import api
from hil.core.recording.reader import read_session
from hil.drivers.canopen import DriveError
from hil.servo.run import ServoRunOptions, run_servo
from tests.cli import hil_here as in_process
from tests.drive_slave import dictionary, serve
from tests.served_here import drive_served_here

pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]


def hil(*args, cwd):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def hil_here(*args, cwd, capsys):
    """``hil ARGS`` run by ``main`` in this process, as :func:`hil` reports it."""
    return in_process(capsys, *args, cwd=cwd)


def test_scan_of_the_emulator_from_outside_lists_the_node_and_says_hil_can_drive_it(tmp_path,
                                                                                   capsys):
    with drive_served_here() as emulator:  # the scan from outside, the drive in this process
        out = hil("drive", "scan", emulator.url, "--json", cwd=tmp_path)
        table = hil_here("drive", "scan", emulator.url, cwd=tmp_path, capsys=capsys)
    assert out.returncode == 0, out.stderr
    [node] = json.loads(out.stdout)["nodes"]
    assert node["node_id"] == 1 and node["device_type"] == 0x0002_0192
    assert node["device_name"] == "hil CiA 402 drive emulator"
    assert node["drivable"] is True and node["problems"] == []
    assert {p["name"] for p in node["pdos"]} >= {"RPDO1", "TPDO1", "TPDO2"}
    assert node["nmt_state"] in ("PRE-OPERATIONAL", "unknown (no heartbeat)")
    assert "can drive: yes, in CST" in table.stdout


@pytest.fixture
def quick_disconnect(monkeypatch):
    """canopen's notifiers poll the bus every 0.1 s, not 1 s: a slave's disconnect waits out
    one poll."""
    monkeypatch.setattr(canopen.Network, "NOTIFIER_CYCLE", 0.1)


@pytest.mark.usefixtures("quick_disconnect")
def test_scan_of_an_independent_drive_names_what_it_lacks_for_csp():
    from hil.drivers.canopen.link import CanLink
    from hil.drivers.canopen.scan import scan

    url = f"virtual://scan-{uuid.uuid4().hex}"
    network, _slave = serve(url, 3)
    bus = can.Bus(interface="virtual", channel=url.removeprefix("virtual://"))
    try:
        link = CanLink(bus)
        [cst] = scan(link)
        [csp] = scan(link, [3], mode="csp")
    finally:
        bus.shutdown()
        network.disconnect()
    assert cst.node_id == 3 and cst.drivable and cst.identity["serial"] == 4711
    assert [p.name for p in cst.pdos] == ["RPDO1", "TPDO1", "TPDO2"]
    assert all(p.valid for p in cst.pdos)  # valid at power-on
    assert not csp.drivable
    assert any("mode CSP not supported" in p for p in csp.problems)
    assert any("0x607A" in p for p in csp.problems)


def test_reset_clears_a_fault_left_behind_and_a_run_can_reset_it_too(tmp_path, capsys):
    strong = tmp_path / "strong.toml"  # a drive whose own limit lets 20 A through
    strong.write_text("[emulator]\nmax_torque_permille = 20000\n")
    with drive_served_here(strong) as emulator:
        with pytest.raises(DriveError):  # beyond the 15 A trip level: EMCY 0x2310, FAULT
            api.run_servo("pid", drive=emulator.url, duration_s=0.2,
                          drive_overrides={"master": {"current_limit_mA": 20000.0}},
                          params={"umax": 20000.0}, reference="hold:position=170",
                          out=str(tmp_path / "fault.mcap"))
        refused = hil_here("servo", "run", "--controller", "pid", "--drive", emulator.url,
                           "--duration", "0.1", "--out", "again.mcap", cwd=tmp_path,
                           capsys=capsys)
        assert refused.returncode == 2
        assert "0x2310" in refused.stderr and "hil drive reset" in refused.stderr
        reset = hil("drive", "reset", emulator.url, cwd=tmp_path)
        assert reset.returncode == 0, reset.stderr
        # the fault reaction may still be braking: the reset waits for it to end
        assert re.search(r"node 1: FAULT( REACTION ACTIVE)? -> SWITCH ON DISABLED", reset.stdout)
        assert "nothing to reset" in hil_here("drive", "reset", emulator.url, cwd=tmp_path,
                                              capsys=capsys).stdout
        # a run with --reset-fault after another fault
        with pytest.raises(DriveError):
            api.run_servo("pid", drive=emulator.url, duration_s=0.2,
                          drive_overrides={"master": {"current_limit_mA": 20000.0}},
                          params={"umax": 20000.0}, reference="hold:position=170",
                          out=str(tmp_path / "fault2.mcap"))
        again = hil("servo", "run", "--controller", "pid", "--drive", emulator.url,
                    "--duration", "0.1", "--reset-fault", "--json", "--out", "ok.mcap",
                    cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert json.loads(again.stdout)["ticks"] == 200


def write_eds(tmp_path, name, change=None):
    od = dictionary(3)
    if change:
        change(od)
    path = tmp_path / f"{name}.eds"
    canopen.export_od(od, str(path), doc_type="eds")
    return path


def _drop(index):
    def change(od):
        del od[index]
    return change


def _resize(od):
    od[0x6071].data_type = canopen.objectdictionary.datatypes.INTEGER32


def _unmappable(od):
    od[0x6064].pdo_mappable = False


@pytest.mark.parametrize(("change", "message"), [
    (_drop(0x6071), "0x6071 is not in it: hil needs it writable and RPDO-mappable, 16 bits, "
                    "to command the current every cycle"),
    (_resize, "0x6071 is 32 bits, hil packs 16"),
    (_unmappable, "0x6064 is not PDO-mappable: hil needs it readable and TPDO-mappable"),
])
@pytest.mark.usefixtures("quick_disconnect")
def test_an_eds_that_lacks_what_hil_needs_stops_before_anything_is_enabled(tmp_path, change,
                                                                          message):
    eds = write_eds(tmp_path, "drive", change)
    url = f"virtual://eds-{uuid.uuid4().hex}"
    network, slave = serve(url, 3)
    observer = can.Bus(interface="virtual", channel=url.removeprefix("virtual://"))
    config = tmp_path / "drive.toml"
    config.write_text(f'[master]\neds = "{eds}"\n')
    try:
        with pytest.raises(DriveError) as error:
            run_servo(ServoRunOptions(controller="pid", drive=url, node=3, duration_s=0.1,
                                      drive_config=str(config), out=str(tmp_path / "x.mcap")))
        frames = []
        while (msg := observer.recv(0)) is not None:
            frames.append(msg)
    finally:
        observer.shutdown()
        network.disconnect()
    assert message in str(error.value) and "\n" not in str(error.value)
    assert slave.state == "SWITCH ON DISABLED"
    rpdo_or_nmt_start = [m for m in frames if m.arbitration_id == 0x203
                         or (m.arbitration_id == 0 and m.data[0] == 0x01)]
    assert rpdo_or_nmt_start == []  # nothing was enabled, no cycle ran
    assert not (tmp_path / "x.mcap").exists()


def test_the_emulators_own_eds_passes_the_check(tmp_path, capsys):
    eds = tmp_path / "emulator.eds"
    assert hil_here("emulate", "drive", "--write-eds", str(eds), cwd=tmp_path,
                    capsys=capsys).returncode == 0
    result = api.run_servo("pid", drive_overrides={"master": {"eds": str(eds)}},
                           duration_s=0.1, out=str(tmp_path / "eds.mcap"))
    assert result["ticks"] == 200
    drive = json.loads(read_session(str(tmp_path / "eds.mcap")).metadata["drive"]["json"])
    assert drive["eds"]["product"] == "hil CiA 402 drive emulator"
    assert drive["scaling"]["increments_per_rev"] == 1 << 20


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".log", ".trc"])
def test_can_log_writes_every_frame_in_a_format_python_can_reads(tmp_path, suffix):
    log = tmp_path / f"run{suffix}"
    result = api.run_servo("pid", duration_s=0.1, can_log=str(log),
                           out=str(tmp_path / "run.mcap"))
    frames = list(can.LogReader(str(log)))
    syncs = [m for m in frames if m.arbitration_id == 0x080]
    tpdo1 = [m for m in frames if m.arbitration_id == 0x181]
    assert len(syncs) >= result["ticks"] and len(tpdo1) >= result["ticks"]
    assert any(m.arbitration_id == 0x601 for m in frames)  # the SDO configuration too


@pytest.mark.realtime
def test_late_tpdos_of_the_emulator_in_real_time_are_never_fresh(tmp_path):
    """The emulator holds its TPDOs 60 ms for 0.1 s every 0.5 s of its time (then the ones
    behind them, in order); with the SYNC counter echo every fresh feedback is, on the wire
    trace, the TPDO pair that carries its SYNC's counter. (Its clock starts with the process:
    the run's first SYNC comes about 1 s later on a quiet machine, seconds later on a loaded
    one; holds from 1.5 s to 6 s of its time put two or more in the 1.5 s run either way.)"""
    config = tmp_path / "drive.toml"
    # a 60 ms hold leaves ~300 cycles in a row stale, the axis driven blind: beyond the
    # default safety limits, which are not what this test is about
    config.write_text('[master]\nstale_cycles = 100000\nsync_echo = "0x2004:0"\n'
                      '[emulator]\nsync_loss_timeout_ms = 5000\n'
                      '[safety]\nenabled = false\n')
    log = tmp_path / "wire.asc"
    holds = [f"delay_tpdo@{start / 2:g}-{start / 2 + 0.1:g}:ms=60" for start in range(3, 13)]
    with api.start_drive_emulator(config, faults=holds, harden=True) as emulator:
        kpis = api.run_servo("pid", drive=emulator.url, realtime=True, duration_s=1.5,
                             drive_config=str(config), can_log=str(log),
                             out=str(tmp_path / "late.mcap"))
    assert kpis["faults"]["late_frames"] > 0 and kpis["stale_feedback"] > 0
    answers, counter = {}, 0
    syncs = 0
    for msg in can.LogReader(str(log)):
        if msg.arbitration_id == 0x080 and msg.dlc == 1:
            syncs += 1
            counter = msg.data[0]
        elif msg.arbitration_id == 0x181 and msg.data[6] == counter:
            answers.setdefault(syncs, struct.unpack_from("<Hi", bytes(msg.data)))
    data = read_session(str(tmp_path / "late.mcap"))
    fresh = 0
    for _, message in data.topic("/drive/feedback"):
        if message["fresh"] and message["cycle"] > 0:
            statusword, position = answers[message["cycle"]]
            assert message["statusword"] == statusword
            assert round(message["position_deg"] / 360 * (1 << 20)) % (1 << 20) == position
            fresh += 1
    # every fresh feedback was checked: the first tick's too, since the clock starts once the
    # primed cycle's answer is back (the enable's SDO-read feedback is no tick's)
    assert fresh == kpis["ticks"] - kpis["stale_feedback"] > 0


def test_plan_says_whether_axes_fit_one_bus_and_the_ways_out(tmp_path, capsys):
    def here(*args):
        return hil_here(*args, cwd=tmp_path, capsys=capsys)

    fits = here("drive", "plan")
    assert fits.returncode == 0, fits.stderr
    assert "1 axis in CST" in fits.stdout and "2000 Hz" in fits.stdout
    assert fits.stdout.rstrip().endswith("fits")
    three = hil("drive", "plan", "--axes", "3", "--rate-hz", "1000", "--json", cwd=tmp_path)
    assert three.returncode == 1
    plan = json.loads(three.stdout)
    assert plan["axes"] == 3 and not plan["fits"] and plan["max_axes"] == 2
    assert plan["bus_time_us"] > 1000 and plan["bus_time"].startswith("worst case")
    assert "master.cycle_period_us >= 1034" in plan["problem"] and "2 buses" in plan["problem"]
    # the config's mapping counts: the SYNC echo adds a byte to each TPDO
    config = tmp_path / "drive.toml"
    config.write_text('[master]\nsync_echo = "0x2004:0"\n')
    echo = json.loads(here("drive", "plan", "--config", str(config), "--json").stdout)
    plain = json.loads(here("drive", "plan", "--json").stdout)
    assert echo["bus_time_us"] > plain["bus_time_us"]
    bad = here("drive", "plan", "--axes", "0")
    assert bad.returncode == 2 and "--axes" in bad.stderr and "Traceback" not in bad.stderr
