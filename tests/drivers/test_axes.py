"""Several drives on one bus (drivers/canopen/axes.py): one SYNC per cycle with every RPDO
before it, each drive's TPDOs to its own master, and a stop on all axes in the same cycles;
against hil's lockstep emulator (two drives on one channel) and against two CiA 402 slaves it
did not write (canopen's LocalNode, tests/drive_slave.py) on a python-can virtual bus."""

from __future__ import annotations

import time
import uuid

import pytest

from hil.drivers.canopen import CanDriveMaster, CanLink, DriveFaultError, DriveMasterConfig
from hil.drivers.canopen.axes import AxisBus, AxisGroup
from hil.drivers.canopen.bus import open_can_bus, parse_can_url
from hil.emulators.drive.runners import LockstepDrive
from hil.protocols.cia301 import EMCY_OVERCURRENT, ERR_REG_CURRENT, SYNC_COB_ID
from hil.protocols.cia402 import CW_QUICK_STOP, SWITCH_ON_DISABLED
from tests.drive_slave import serve


def lockstep_group(node_ids=(1, 2)):
    emulator = LockstepDrive(node_ids=node_ids)
    observer = emulator.attach_bus()  # what is on the wire, in order
    bus = AxisBus(CanLink(emulator.master_bus), node_ids)
    masters = [CanDriveMaster(bus.node_link(n), DriveMasterConfig(node_id=n), clock=emulator)
               for n in node_ids]
    return emulator, observer, AxisGroup(bus, masters)


def wire(observer):
    frames = []
    while (frame := observer.recv_frame()) is not None:
        frames.append(frame)
    return frames


def test_one_sync_per_cycle_every_rpdo_before_it_each_axis_its_own_feedback():
    emulator, observer, group = lockstep_group()
    start = group.start()
    wire(observer)  # the set-up's frames
    syncs_before = [node.sync_count for node in emulator.nodes]
    for _ in range(400):
        group.send_currents([300.0, -300.0])
        feedbacks = group.receive()
    frames = wire(observer)
    cycles = group.bus.cycles
    synced = [n.sync_count - s for n, s in zip(emulator.nodes, syncs_before, strict=True)]
    group.close()
    syncs = [i for i, (can_id, _) in enumerate(frames) if can_id == SYNC_COB_ID]
    assert len(syncs) == 400 == cycles
    # each cycle: RPDO of node 1, RPDO of node 2, then the SYNC; the TPDOs after it
    for k, at in enumerate(syncs):
        before = [can_id for can_id, _ in frames[(syncs[k - 1] + 1 if k else 0):at]]
        assert [c for c in before if 0x200 < c < 0x280] == [0x201, 0x202], k
    assert synced == [400, 400]
    assert all(f.fresh for f in feedbacks)
    moved = [f.position_deg - s.position_deg for f, s in zip(feedbacks, start, strict=True)]
    assert moved[0] > 1.0 and moved[1] < -1.0  # each axis its own current, its own way
    # the same plant, mirrored (to the encoder count: it floors either way)
    assert moved[0] == pytest.approx(-moved[1], abs=2 * 360 / 2**20)


def test_a_fault_on_one_axis_stops_every_axis_in_the_same_cycle():
    emulator, observer, group = lockstep_group()
    group.start()
    for _ in range(100):
        group.send_currents([300.0, 300.0])
        group.receive()
    wire(observer)
    emulator.nodes[1].states.fault(EMCY_OVERCURRENT, ERR_REG_CURRENT)  # drive 2 trips
    group.send_currents([300.0, 300.0])
    with pytest.raises(DriveFaultError, match="drive node 2 reports FAULT"):
        group.receive()
    group.safe_state()
    frames = wire(observer)
    # the quick stop of the axis still enabled and the SYNC that takes it: one cycle; the
    # faulted drive is already torque-free
    quick = [i for i, (can_id, data) in enumerate(frames)
             if can_id == 0x201 and int.from_bytes(data[:2], "little") == CW_QUICK_STOP]
    assert quick and frames[quick[0] + 1][0] == SYNC_COB_ID
    assert emulator.nodes[0].state == SWITCH_ON_DISABLED
    assert emulator.nodes[1].state == "FAULT"
    group.close()


def test_a_stop_takes_every_axis_to_its_safe_state_in_the_same_cycles():
    emulator, observer, group = lockstep_group((1, 2, 3))
    group.start()
    for _ in range(200):
        group.send_currents([400.0, -400.0, 200.0])
        group.receive()
    wire(observer)
    group.safe_state()
    frames = wire(observer)
    cycles = []  # per SYNC: the controlword of each node's RPDO before it
    words: dict[int, int] = {}
    for can_id, data in frames:
        if 0x200 < can_id < 0x280:
            words[can_id - 0x200] = int.from_bytes(data[:2], "little")
        elif can_id == SYNC_COB_ID:
            cycles.append(dict(words))
            words = {}
    assert cycles and all(set(cycle) == {1, 2, 3} for cycle in cycles)
    assert all(len(set(cycle.values())) == 1 for cycle in cycles)  # the same word for all
    assert cycles[0][1] == CW_QUICK_STOP and cycles[-1][1] == 0  # then disable voltage
    assert [node.state for node in emulator.nodes] == [SWITCH_ON_DISABLED] * 3
    group.close()


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_two_independent_slaves_share_one_sync_and_answer_their_own_master():
    url = f"virtual://axes-{uuid.uuid4().hex}"
    slaves = [serve(url, node_id) for node_id in (3, 4)]
    bus = AxisBus(CanLink(open_can_bus(parse_can_url(url))), [3, 4])
    # threads answer here, not drives: a patient deadline (what is tested is who hears what)
    config = {"cycle_period_s": 0.002, "rx_timeout_s": 0.0015, "stale_cycles": 1000}
    group = AxisGroup(bus, [CanDriveMaster(bus.node_link(n),
                                           DriveMasterConfig(node_id=n, **config))
                            for n in (3, 4)])
    try:
        group.start()
        first = [slave.syncs for _, slave in slaves]
        next_t = time.monotonic()
        for _ in range(200):
            group.send_currents([200.0, -200.0])
            feedbacks = group.receive()
            next_t += 0.002
            time.sleep(max(0.0, next_t - time.monotonic()))
        # the slaves' threads may still be at the last SYNC (a loaded machine): wait for them,
        # a bounded while, before counting what they heard
        until = time.monotonic() + 2.0
        while time.monotonic() < until and \
                any(slave.syncs - f < 200 for (_, slave), f in zip(slaves, first, strict=True)):
            time.sleep(0.005)
        counts = [slave.syncs - f for (_, slave), f in zip(slaves, first, strict=True)]
        group.safe_state()
        states = [slave.state for _, slave in slaves]
    finally:
        group.close()
        for network, _ in slaves:
            network.disconnect()
    assert counts == [200, 200]  # one SYNC per cycle, heard by both
    assert [f.statusword & 0x6F for f in feedbacks] == [0x27, 0x27]  # both OPERATION ENABLED
    assert states == [SWITCH_ON_DISABLED, SWITCH_ON_DISABLED]


def test_a_frame_already_received_is_found_behind_another_drives_frames():
    """The bus routes every frame already here before a time-out counts: a master polling
    (time-out 0) finds its TPDO behind another drive's heartbeat, not a stale cycle (a run
    under load once counted its stop's answers late this way)."""
    emulator = LockstepDrive(node_ids=(1, 2))
    bus = AxisBus(CanLink(emulator.master_bus), (1, 2))
    while emulator.master_bus.recv_frame() is not None:
        pass  # the boot-up messages
    node_bus = emulator.attach_bus()
    node_bus.send_frames([(0x702, b"\x05"), (0x282, bytes(6)), (0x181, b"\x37\x02\0\0\0\0")])
    assert bus.recv(bus.node_link(1), 0.0) == (0x181, b"\x37\x02\0\0\0\0")
    assert bus.recv(bus.node_link(2), 0.0) == (0x702, b"\x05")  # routed on the way
    assert bus.recv(bus.node_link(1), 0.0) is None  # nothing else is node 1's
    node_bus.shutdown()
    emulator.close()
