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


class FrameByFrame:
    """A bus's frames one at a time, as every bus but the in-process one gives them (no
    ``take_frames``)."""

    def __init__(self, bus):
        self.bus, self.channel_info = bus, bus.channel_info

    def send_frames(self, frames):
        self.bus.send_frames(frames)

    def recv_frame(self, timeout=None):
        return self.bus.recv_frame(timeout)

    def shutdown(self):
        self.bus.shutdown()


def lockstep_group(node_ids=(1, 2), frame_by_frame=False):
    emulator = LockstepDrive(node_ids=node_ids)
    observer = emulator.attach_bus()  # what is on the wire, in order
    master_bus = FrameByFrame(emulator.master_bus) if frame_by_frame else emulator.master_bus
    bus = AxisBus(CanLink(master_bus), node_ids)
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


def group_run(frame_by_frame):
    """Three axes for 300 cycles, node 2 tripping at cycle 200, then the stop: each cycle's
    feedbacks (the wall-clock rtt left out) or the error, the wire, the masters' counters."""
    emulator, observer, group = lockstep_group((1, 2, 3), frame_by_frame)
    assert group.bus.link.takes_frames is not frame_by_frame
    seen = [group.start()]
    for k in range(300):
        if k == 200:
            emulator.nodes[1].states.fault(EMCY_OVERCURRENT, ERR_REG_CURRENT)
        group.send_currents([300.0, -300.0, 100.0])
        try:
            seen.append([f._replace(rtt_us=0.0) for f in group.receive()])
        except DriveFaultError as exc:
            seen.append(str(exc))
            break
    group.safe_state()
    frames = wire(observer)
    stats = [master.stats for master in group.masters]
    group.close()
    emulator.close()
    return seen, frames, stats


def test_frames_taken_at_once_go_where_frame_by_frame_they_would():
    """The in-process bus hands every waiting frame in one call, routed in one pass (each
    COB-ID seen once by its route): the same cycles, feedbacks, fault, stop and wire as a bus
    read frame by frame."""
    taken, by_frame = group_run(False), group_run(True)
    assert isinstance(taken[0][-1], str) and "drive node 2 reports FAULT" in taken[0][-1]
    assert taken == by_frame


def test_a_route_learnt_is_forgotten_when_the_watched_ids_change():
    """A COB-ID routed once goes straight to its master's inbox, until the ids the link
    watches change: then it is checked for an echo again."""
    emulator = LockstepDrive(node_ids=(1, 2))
    bus = AxisBus(CanLink(emulator.master_bus), (1, 2))
    while emulator.master_bus.recv_frame() is not None:
        pass  # the boot-up messages
    node_bus = emulator.attach_bus()
    node_bus.send_frames([(0x181, b"\x01")])
    assert bus.recv(bus.node_link(1), 0.0) == (0x181, b"\x01")
    echoes = []
    bus.link.own_echo = lambda frame: echoes.append(frame) or True
    bus.link.watched_ids = frozenset({SYNC_COB_ID, 0x181})
    node_bus.send_frames([(0x181, b"\x02")])
    assert bus.recv(bus.node_link(1), 0.0) is None  # taken for the link's own echo
    assert echoes == [(0x181, b"\x02")]
    node_bus.shutdown()
    emulator.close()
