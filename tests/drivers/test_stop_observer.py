"""The safe stop told cycle by cycle (``CanDriveMaster.on_stop_cycle``): every quick-stop cycle
and the disable-voltage cycle, the drive's own feedback of each, on one drive and on several
stopped together; an observer that fails never stops the stop. Against hil's lockstep emulator
and against a CiA 402 slave hil did not write (canopen's LocalNode, tests/drive_slave.py),
whose log of the TPDOs it sent is what the session's ``/drive/stop`` must hold."""

from __future__ import annotations

import struct
import uuid

import pytest

from hil.core.recording.reader import read_session
from hil.drivers.canopen import CanDriveMaster, CanLink, DriveMasterConfig
from hil.drivers.canopen.axes import AxisBus, AxisGroup
from hil.emulators.drive.runners import LockstepDrive
from hil.protocols.cia402 import (
    CW_DISABLE_VOLTAGE,
    CW_QUICK_STOP,
    QUICK_STOP_ACTIVE,
    SWITCH_ON_DISABLED,
    state_of,
)
from hil.servo.config import load_drive_config
from hil.servo.rig import open_drive
from hil.servo.run import ServoRunOptions, run_servo
from tests.drive_slave import INCREMENTS, serve


class Events:
    """An on_event sink with the signature of Session.event."""

    def __init__(self):
        self.kinds = []

    def __call__(self, kind, message, level="info", source="", **data):
        self.kinds.append(kind)


def controlwords(frames, node_id):
    return [struct.unpack_from("<H", data)[0] for can_id, data in frames
            if can_id == 0x200 + node_id]


def wire(observer):
    frames = []
    while (frame := observer.recv_frame()) is not None:
        frames.append(frame)
    return frames


def running_drive(events):
    """The emulated drive, enabled and turning at about 450 deg/s (800 mA for 0.2 s)."""
    master = open_drive("emulated", load_drive_config(), on_event=events)
    master.start()
    for _ in range(400):
        master.exchange(800.0)
    return master


def test_each_cycle_of_the_stop_is_told_with_the_drives_feedback():
    master = running_drive(Events())
    observer = master.emulator.attach_bus()
    told = []
    master.on_stop_cycle = told.append
    master.safe_state()
    words = controlwords(wire(observer), master.node_id)
    assert len(told) == len(words) > 10  # one call per cycle of the stop, the last included
    assert words[-1] == CW_DISABLE_VOLTAGE and set(words[:-1]) == {CW_QUICK_STOP}
    assert [f.cycle for f in told] == list(range(told[0].cycle, told[0].cycle + len(told)))
    assert told[0].velocity_deg_s > 300.0 and state_of(told[0].statusword) == QUICK_STOP_ACTIVE
    assert told[-1].state == SWITCH_ON_DISABLED and abs(told[-1].velocity_deg_s) < 5.0
    assert told[-1].position_deg == pytest.approx(master.emulator.node.plant.position_deg,
                                                  abs=0.01)
    master.safe_state()  # already stopped: nothing more to tell
    assert len(told) == len(words)
    master.close()


def test_an_observer_that_fails_is_dropped_and_the_stop_goes_on():
    events = Events()
    master = running_drive(events)
    calls = []

    def broken(feedback):
        calls.append(feedback)
        raise RuntimeError("recorder gone")

    master.on_stop_cycle = broken
    master.safe_state()
    assert len(calls) == 1 and master.on_stop_cycle is None
    node = master.emulator.node
    assert node.state == SWITCH_ON_DISABLED and abs(node.plant.velocity_deg_s) < 5.0
    assert events.kinds[-2:] == ["drive.stop_observer_failed", "drive.safe_stop"]
    master.close()


def test_drives_stopped_together_each_tell_every_cycle():
    emulator = LockstepDrive(node_ids=(1, 2))
    bus = AxisBus(CanLink(emulator.master_bus), (1, 2))
    masters = [CanDriveMaster(bus.node_link(n), DriveMasterConfig(node_id=n), clock=emulator)
               for n in (1, 2)]
    group = AxisGroup(bus, masters)
    group.start()
    for _ in range(400):
        group.send_currents([800.0, -300.0])
        group.receive()
    told: dict[int, list] = {1: [], 2: []}
    for master in masters:
        master.on_stop_cycle = told[master.node_id].append
    group.close()
    emulator.close()
    assert len(told[1]) == len(told[2]) > 10  # the same cycles: the faster axis sets them
    assert [f.cycle for f in told[1]] == [f.cycle for f in told[2]]
    assert told[1][0].velocity_deg_s > 300.0 and told[2][0].velocity_deg_s < -100.0
    assert all(f[-1].state == SWITCH_ON_DISABLED for f in told.values())


@pytest.mark.slow
def test_the_stop_of_a_drive_hil_did_not_write_is_in_the_session_as_it_sent_it(tmp_path):
    url = f"virtual://stop-{uuid.uuid4().hex}"
    network, slave = serve(url, 3)
    config = tmp_path / "slave.toml"
    config.write_text("")
    try:
        result = run_servo(ServoRunOptions(
            controller="pid", reference="sine:amplitude=90,frequency=1", drive=url, node=3,
            duration_s=0.5, drive_config=str(config), out=str(tmp_path / "slave.mcap")))
    finally:
        network.disconnect()
    data = read_session(result.session_path)
    stop = [message for _, message in data.topic("/drive/stop")]
    last_tick = data.topic("/drive/feedback")[-1][1]
    assert stop[0]["cycle"] == last_tick["cycle"] + 2  # the stop, after the run's last command
    sent = {entry["sync"]: entry for entry in slave.log}
    for message in stop:  # each what the slave sent for that SYNC
        tpdo1 = bytes.fromhex(sent[message["cycle"]]["tpdo1"])
        statusword, position = struct.unpack_from("<Hi", tpdo1)
        assert message["fresh"] and message["statusword"] == statusword
        assert round(message["position_deg"] / 360.0 * INCREMENTS) % INCREMENTS == \
            position % INCREMENTS
    assert state_of(stop[0]["statusword"]) == QUICK_STOP_ACTIVE
    assert state_of(stop[-1]["statusword"]) == SWITCH_ON_DISABLED == slave.state
