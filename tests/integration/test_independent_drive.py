"""hil's master against a CiA 402 drive it did not write (tests/drive_slave.py: canopen's
LocalNode, its own object dictionary: 17-bit encoder, 2 A rated current, PDOs valid at
power-on, CiA 301 remapping rules), over python-can's ``virtual`` interface in this process
and over ``udp_multicast`` from another process: enable, run, safe stop, and every feedback
marked fresh equal to the slave's TPDO of its own SYNC, also when the slave falls behind."""

import json
import os
import signal
import socket
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from hil.core.recording.reader import read_session
from hil.servo.run import ServoRunOptions, run_servo
from tests.drive_slave import INCREMENTS, RATED_MA, serve

pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
NODE = 3


def check_feedback_against(log, path):
    """Every fresh feedback of the session at ``path`` against the slave's log; the number
    of fresh cycles compared."""
    sent = {entry["sync"]: entry for entry in log}
    data = read_session(path)
    compared = 0
    for _, message in data.topic("/drive/feedback"):
        cycle = message["cycle"]
        if not message["fresh"] or cycle == 0:  # cycle 0: read by SDO at enable
            continue
        entry = sent[cycle]
        statusword = int.from_bytes(bytes.fromhex(entry["tpdo1"])[:2], "little")
        position = int.from_bytes(bytes.fromhex(entry["tpdo1"])[2:6], "little", signed=True)
        torque = int.from_bytes(bytes.fromhex(entry["tpdo2"])[4:6], "little", signed=True)
        assert message["statusword"] == statusword, cycle
        assert round(message["position_deg"] / 360.0 * INCREMENTS) % INCREMENTS == position, \
            cycle
        assert message["current_mA"] == pytest.approx(torque * RATED_MA / 1000, abs=0.5), cycle
        compared += 1
    return compared


def session(tmp_path, url, name, config="", **options):
    drive_config = tmp_path / f"{name}.toml"
    drive_config.write_text(config)
    return run_servo(ServoRunOptions(
        controller="pid", reference="sine:amplitude=2,frequency=1", drive=url, node=NODE,
        duration_s=0.5, out=str(tmp_path / f"{name}.mcap"), drive_config=str(drive_config),
        **options))


def test_virtual_bus_enable_run_safe_stop_and_every_feedback_is_its_syncs(tmp_path):
    url = f"virtual://independent-{uuid.uuid4().hex}"
    network, slave = serve(url, NODE)
    try:
        result = session(tmp_path, url, "virtual")
    finally:
        network.disconnect()
    kpis = result.kpis
    assert kpis["ticks"] == 1000 and kpis["stale_feedback"] == 0
    assert kpis["faults"]["late_frames"] == 0
    assert slave.state == "SWITCH ON DISABLED"  # the safe stop reached the slave
    assert check_feedback_against(slave.log, result.session_path) == 999
    # its scaling came from it: 17-bit encoder, 2 A rated current
    events = [m for _, m in read_session(result.session_path).topic("/events")
              if m["kind"] == "drive.configured"]
    assert events[0]["data"]["scaling"]["increments_per_rev"] == INCREMENTS
    assert events[0]["data"]["scaling"]["rated_current_ma"] == RATED_MA


def test_a_slave_that_falls_behind_never_gives_an_old_answer_as_fresh(tmp_path):
    """At SYNC 200 the slave falls one cycle behind: its answer lands after SYNC 201, just
    before 201's own. Bound to its SYNC by the echo, that pair is late, never 201's: cycle 200
    is stale, and every fresh feedback is the one its SYNC got."""
    url = f"virtual://independent-{uuid.uuid4().hex}"
    network, slave = serve(url, NODE, behind_at=200)
    # the late cycle ends at the lockstep timeout (its answer never comes before the next
    # SYNC): 2 s, which a loaded machine's slave thread also needs at times (0.3 s was once
    # too short for an ordinary cycle's answer at nice 10 beside 4 workers)
    echoed = '[master]\nsync_echo = "0x2100:0"\nlockstep_timeout_ms = 2000\n'
    try:
        result = session(tmp_path, url, "late", echoed)
    finally:
        network.disconnect()
    kpis = result.kpis
    assert kpis["faults"]["late_frames"] == 2 and kpis["stale_feedback"] == 1
    compared = check_feedback_against(slave.log, result.session_path)
    assert compared == kpis["ticks"] - 1 - kpis["stale_feedback"] == 998


def free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.mark.timeout(60)
def test_udp_multicast_from_another_process(tmp_path):
    url = f"udp_multicast://239.0.0.1?port={free_udp_port()}"
    log = tmp_path / "slave.json"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    slave = subprocess.Popen([sys.executable, str(ROOT / "tests" / "drive_slave.py"), url,
                              str(NODE), str(log)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert slave.stdout.readline().strip() == "serving"
        result = session(tmp_path, url, "udp")
    finally:
        slave.send_signal(signal.SIGTERM)
        slave.wait(timeout=10)
    assert result.kpis["ticks"] == 1000 and result.kpis["stale_feedback"] == 0
    assert check_feedback_against(json.loads(log.read_text()), result.session_path) == 999
