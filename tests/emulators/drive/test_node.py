"""The emulated CiA 402 node at frame level: NMT, SDO (with abort codes), PDOs, heartbeat, EMCY,
faults, and frames it must not trust. Lockstep on a python-can virtual bus, so nothing here
depends on wall-clock timing, except the one SYNC-loss test that needs a real-time node."""

import random
import struct
import time

import can
import pytest

from hil.contracts import PollBudget
from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.node import LOCKSTEP_POLL_NS, DriveNode
from hil.emulators.drive.od import build_object_dictionary, iter_variables
from hil.emulators.drive.runners import BusRunner, LockstepDrive, bus_sender
from hil.protocols.cia402 import STATUSWORD_MASKS, enable_steps


class Wire:
    """A raw test master on the lockstep drive's bus: send a frame, pump, collect the answers."""

    def __init__(self, **config):
        self.drive = LockstepDrive(DriveEmulatorConfig(**config))
        self.node = self.drive.node
        self.bus = self.drive.master_bus
        self.received: list[can.Message] = []
        self.collect()

    def send(self, can_id, data=b""):
        self.bus.send(can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=False))
        self.drive.pump()
        return self.collect()

    def collect(self):
        new = []
        while (msg := self.bus.recv(0)) is not None:
            new.append(msg)
        self.received += new
        return new

    def sdo(self, request):
        answers = [m for m in self.send(0x601, request) if m.arbitration_id == 0x581]
        assert len(answers) == 1, answers
        return bytes(answers[0].data)

    def read(self, index, sub=0):
        return self.sdo(struct.pack("<BHB", 0x40, index, sub) + bytes(4))

    def write(self, index, sub, value, fmt):
        data = struct.pack(fmt, value)
        command = 0x23 | ((4 - len(data)) << 2)
        return self.sdo(struct.pack("<BHB", command, index, sub) + data.ljust(4, b"\0"))

    def statusword(self):
        return struct.unpack_from("<H", self.read(0x6041), 4)[0]

    def emcy_codes(self, frames=None):
        frames = self.received if frames is None else frames
        return [struct.unpack_from("<H", m.data)[0] for m in frames if m.arbitration_id == 0x81]

    def close(self):
        self.drive.close()


@pytest.fixture
def wire():
    w = Wire()
    yield w
    w.close()


def abort_code(response):
    assert response[0] == 0x80, f"expected an SDO abort, got {response.hex()}"
    return struct.unpack_from("<I", response, 4)[0]


def in_state(statusword, state):
    mask, value = STATUSWORD_MASKS[state]
    return statusword & mask == value


def enable(w, mode=10):
    """NMT start, mode, then the controlword walk by SDO to OPERATION ENABLED."""
    w.write(0x6060, 0, mode, "<b")
    w.send(0x000, [0x01, 1])
    for controlword, _state in enable_steps():
        w.write(0x6040, 0, controlword, "<H")
    assert in_state(w.statusword(), "OPERATION ENABLED")


def test_boots_into_switch_on_disabled_with_a_boot_up_message(wire):
    assert [(m.arbitration_id, bytes(m.data)) for m in wire.received] == [(0x701, b"\x00")]
    statusword = wire.statusword()
    assert in_state(statusword, "SWITCH ON DISABLED")
    assert statusword == 0x0250
    device_type = struct.unpack_from("<I", wire.read(0x1000), 4)[0]
    assert device_type == 0x00020192


def test_every_readable_object_uploads_with_its_size(wire):
    od = build_object_dictionary(1)
    for var in iter_variables(od):
        response = wire.read(var.index, var.subindex)
        if var.data_type == 0x9:  # visible string: segmented, size announced
            assert response[0] & 0xE3 == 0x41
            continue
        assert response[0] & 0xE3 == 0x43, (hex(var.index), var.subindex, response.hex())
        assert 4 - ((response[0] >> 2) & 3) == len(var) // 8


@pytest.mark.parametrize(("request_", "code"), [
    (struct.pack("<BHB", 0x40, 0x1234, 0) + bytes(4), 0x06020000),   # no such object
    (struct.pack("<BHB", 0x40, 0x1016, 2) + bytes(4), 0x06090011),   # no such sub-index
    (struct.pack("<BHB", 0x40, 0x6041, 1) + bytes(4), 0x06090011),   # variable with sub-index
    (struct.pack("<BHBH", 0x2B, 0x6041, 0, 1) + bytes(2), 0x06010002),  # read-only
    (struct.pack("<BHBI", 0x23, 0x6040, 0, 1), 0x06070010),          # 4 bytes to a u16
    (struct.pack("<BHBb", 0x2F, 0x6060, 0, 2) + bytes(3), 0x06090030),  # unsupported mode (VL)
    (struct.pack("<BHBI", 0x23, 0x6075, 0, 0), 0x06090032),          # rated current 0
    (struct.pack("<BHBI", 0x23, 0x1006, 0, 750), 0x06090030),        # not a plant multiple
    # found by the fuzz campaign: a SYNC after it stepped the plant 8.6 million times
    (struct.pack("<BHBI", 0x23, 0x1006, 0, 4_294_967_000), 0x06090031),  # hours per SYNC
    (struct.pack("<BHBh", 0x2B, 0x605A, 0, 3) + bytes(2), 0x06090030),  # quick-stop option 3
    (struct.pack("<BHBI", 0x23, 0x1005, 0, 0x40000080), 0x06090030),  # we do not make SYNC
    (struct.pack("<BHBI", 0x23, 0x1A00, 1, 0x60640020), 0x06010000),  # mapping of a valid PDO
    (struct.pack("<BHBI", 0x23, 0x1016, 1, (1 << 16) | 100), 0x06090030),  # watch ourselves
    (bytes([0xE0]) + bytes(7), 0x05040001),                           # no such command
    (bytes([0x60]) + bytes(7), 0x05040001),                           # segment, no transfer
])
def test_bad_sdo_requests_get_the_cia_301_abort_code(wire, request_, code):
    assert abort_code(wire.sdo(request_)) == code
    assert wire.node.internal_errors == 0


def test_sdo_with_a_wrong_length_is_aborted(wire):
    response = wire.sdo(bytes([0x40, 0x41, 0x60, 0x00, 0x00]))
    assert abort_code(response) == 0x05040001
    assert response[1:4] == bytes([0x41, 0x60, 0x00])


def test_pdo_remapping_follows_the_cia_301_procedure(wire):
    tpdo2 = 0x1801
    assert wire.write(tpdo2, 1, 0x80000281, "<I")[0] == 0x60            # invalidate
    assert abort_code(wire.write(0x1A01, 1, 0x60770010, "<I")) == 0x06010000  # sub0 != 0
    assert wire.write(0x1A01, 0, 0, "<B")[0] == 0x60
    assert abort_code(wire.write(0x1A01, 1, 0x10000020, "<I")) == 0x06040041  # not mappable
    assert abort_code(wire.write(0x1A01, 1, 0x60640010, "<I")) == 0x06040041  # wrong size
    assert abort_code(wire.write(0x1A01, 1, 0x12340010, "<I")) == 0x06020000  # no object
    for sub in (1, 2, 3):
        assert wire.write(0x1A01, sub, 0x60640020, "<I")[0] == 0x60
    assert abort_code(wire.write(0x1A01, 0, 3, "<B")) == 0x06040042      # 96 bits
    assert wire.write(0x1A01, 0, 2, "<B")[0] == 0x60
    assert abort_code(wire.write(tpdo2, 2, 241, "<B")) == 0x06090030     # reserved
    assert wire.write(tpdo2, 2, 2, "<B")[0] == 0x60                       # every 2nd SYNC
    assert wire.write(tpdo2, 1, 0x281, "<I")[0] == 0x60                   # valid again
    wire.send(0x000, [0x01, 1])
    sizes = []
    for _ in range(4):
        sizes.append([len(m.data) for m in wire.send(0x080) if m.arbitration_id == 0x281])
    assert sizes == [[], [8], [], [8]]


def test_nmt_states_gate_pdo_sdo_and_show_in_the_heartbeat(wire):
    wire.write(0x1017, 0, 10, "<H")
    assert not [m for m in wire.send(0x080) if m.arbitration_id in (0x181, 0x281)]  # pre-op
    wire.send(0x000, [0x01, 0])  # start all nodes
    answer = wire.send(0x080)
    assert {m.arbitration_id for m in answer} >= {0x181, 0x281}
    wire.send(0x000, [0x01, 2])  # another node: ignored
    wire.send(0x000, [0x02])     # wrong length: ignored
    assert wire.node.nmt_state == 0x05
    for _ in range(25):          # 25 SYNC of 500 us: heartbeats every 10 ms of SYNC time
        wire.send(0x080)
    beats = [bytes(m.data) for m in wire.received if m.arbitration_id == 0x701]
    assert beats[-1] == b"\x05" and len(beats) >= 2
    wire.send(0x000, [0x02, 1])  # stopped: no SDO, no PDO
    assert wire.send(0x601, struct.pack("<BHB", 0x40, 0x1000, 0) + bytes(4)) == []
    assert wire.send(0x080) == []
    wire.send(0x000, [0x80, 1])
    assert wire.read(0x1000)[0] == 0x43


def test_reset_node_restores_defaults_and_boots_again(wire):
    wire.write(0x1017, 0, 10, "<H")
    wire.write(0x6060, 0, 10, "<b")
    frames = wire.send(0x000, [0x81, 1])
    assert (0x701, b"\x00") in [(m.arbitration_id, bytes(m.data)) for m in frames]
    assert struct.unpack_from("<H", wire.read(0x1017), 4)[0] == 0
    assert struct.unpack_from("<b", wire.read(0x6061), 4)[0] == 0
    assert in_state(wire.statusword(), "SWITCH ON DISABLED")


def test_reset_communication_keeps_the_application_parameters(wire):
    wire.write(0x1017, 0, 10, "<H")
    wire.write(0x6060, 0, 8, "<b")
    frames = wire.send(0x000, [0x82, 1])
    assert (0x701, b"\x00") in [(m.arbitration_id, bytes(m.data)) for m in frames]
    assert struct.unpack_from("<H", wire.read(0x1017), 4)[0] == 0
    assert struct.unpack_from("<b", wire.read(0x6061), 4)[0] == 8


def test_rpdo_of_the_wrong_length_is_not_processed_and_reported(wire):
    enable(wire)
    short = wire.send(0x201, [0x0F, 0x00, 0x10])  # 3 bytes, the mapping needs 4
    assert wire.emcy_codes(short) == [0x8210]
    assert wire.emcy_codes(wire.send(0x201, [0x0F, 0x00, 0x10])) == []  # reported once
    wire.send(0x080)
    assert wire.node.plant.applied_current_ma == 0.0
    assert wire.send(0x201, [0x0F, 0x00, 0x64, 0x00]) == []  # a good one clears the latch
    long = wire.send(0x201, [0x0F, 0x00, 0x64, 0x00, 0xAA])   # 5 bytes: used, reported
    assert wire.emcy_codes(long) == [0x8220]
    wire.send(0x080)
    assert wire.node.plant.applied_current_ma == 100.0


def test_sync_with_a_data_length_above_one_is_reported_and_ignored(wire):
    wire.send(0x000, [0x01, 1])
    frames = wire.send(0x080, [1, 2, 3])
    assert wire.emcy_codes(frames) == [0x8240]
    assert wire.node.sync_count == 0
    wire.send(0x080, [7])  # a SYNC counter byte is fine
    assert wire.node.sync_count == 1


def test_random_frames_never_crash_the_node():
    w = Wire()
    rng = random.Random(402)
    ids = [0x000, 0x080, 0x201, 0x601, 0x77F, 0x701, 0x123]
    for _ in range(3000):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
        w.send(rng.choice(ids), data)
        if rng.random() < 0.01:
            w.send(0x000, [0x80, 1])  # keep it talking
    assert w.node.internal_errors == 0
    w.send(0x000, [0x81, 1])
    assert in_state(w.statusword(), "SWITCH ON DISABLED")
    w.close()


def test_over_current_command_trips_emcy_2310_and_fault_until_reset(wire):
    enable(wire)
    trip = struct.unpack_from("<H", wire.read(0x2002), 4)[0]
    frames = wire.send(0x201, struct.pack("<Hh", 0x0F, trip + 1)) + wire.send(0x080)
    assert wire.emcy_codes(frames) == [0x2310]
    assert in_state(wire.statusword(), "FAULT")
    assert struct.unpack_from("<H", wire.read(0x603F), 4)[0] == 0x2310
    wire.write(0x6040, 0, 0x0F, "<H")  # no reset without the bit 7 edge
    assert in_state(wire.statusword(), "FAULT")
    reset = wire.write(0x6040, 0, 0x8F, "<H")  # rising edge of bit 7
    assert reset[0] == 0x60
    assert in_state(wire.statusword(), "SWITCH ON DISABLED")
    assert 0x0000 in wire.emcy_codes()
    assert struct.unpack_from("<B", wire.read(0x1001), 4)[0] == 0


def test_master_heartbeat_loss_faults_after_the_consumer_time():
    w = Wire()
    w.write(0x1016, 1, (0x7F << 16) | 20, "<I")  # watch node 127, 20 ms
    enable(w)
    for k in range(200):  # heartbeat every 10 ms (20 SYNC) for 100 ms
        if k % 20 == 0:
            w.send(0x77F, [0x05])
        w.send(0x201, struct.pack("<Hh", 0x0F, 0))
        w.send(0x080)
    assert w.emcy_codes() == []
    last_beat_sync = 180  # the last heartbeat came after 180 SYNC
    for _ in range(100):  # the master goes silent, SYNC goes on
        frames = w.send(0x080)
        if w.emcy_codes(frames):
            break
    else:
        pytest.fail("no EMCY after the heartbeat stopped")
    silent_ms = (w.node.sync_count - last_beat_sync) * 0.5
    assert 20 < silent_ms <= 21  # exactly the consumer time, at SYNC resolution
    emcy = next(m for m in frames if m.arbitration_id == 0x81)
    assert struct.unpack_from("<HB", emcy.data) == (0x8130, 0x11)
    assert emcy.data[3] == 0x01  # cause: heartbeat
    assert in_state(w.statusword(), "FAULT")
    w.close()


def test_sync_loss_faults_a_real_time_node_within_its_timeout():
    channel = "sync-loss-test"
    node_bus = can.Bus(interface="virtual", channel=channel)
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    node = DriveNode(DriveEmulatorConfig(sync_loss_timeout_ms=200), send=bus_sender(node_bus))
    runner = BusRunner(node, node_bus).start()
    try:
        def send(can_id, data=b""):
            bus.send(can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=False))

        send(0x601, struct.pack("<BHBb", 0x2F, 0x6060, 0, 10) + bytes(3))
        send(0x000, [0x01, 1])
        for controlword in (0x06, 0x07, 0x0F):
            send(0x601, struct.pack("<BHBH", 0x2B, 0x6040, 0, controlword) + bytes(2))
        for _ in range(20):
            send(0x201, struct.pack("<Hh", 0x0F, 0))
            last_sync = time.monotonic()  # the node sees the SYNC later, never earlier
            send(0x080)
            time.sleep(0.002)
        deadline = last_sync + 5.0
        emcy = None
        while time.monotonic() < deadline:
            msg = bus.recv(0.1)
            if msg is not None and msg.arbitration_id == 0x81:
                emcy = msg
                break
        assert emcy is not None, "no EMCY after SYNC stopped"
        assert time.monotonic() - last_sync >= 0.2  # never before the configured timeout
        assert struct.unpack_from("<H", emcy.data)[0] == 0x8130 and emcy.data[3] == 0x02
        assert node.state == "FAULT"
    finally:
        runner.stop()
        node_bus.shutdown()
        bus.shutdown()


def test_cycle_period_of_two_plant_periods_steps_twice_per_sync(wire):
    assert wire.write(0x1006, 0, 1000, "<I")[0] == 0x60
    enable(wire)
    wire.send(0x201, struct.pack("<Hh", 0x0F, 100))
    for _ in range(100):
        wire.send(0x080)
    assert wire.node.plant.steps == 200
    assert wire.node.plant.time_s == pytest.approx(0.1)


def test_csp_mode_follows_a_position_target(wire):
    wire.write(0x1400, 1, 0x80000201, "<I")
    wire.write(0x1600, 0, 0, "<B")
    wire.write(0x1600, 2, 0x607A0020, "<I")
    wire.write(0x1600, 0, 2, "<B")
    wire.write(0x1400, 1, 0x201, "<I")
    enable(wire, mode=8)
    target = 1 << 16  # 22.5 deg
    for _ in range(1000):  # 0.5 s
        wire.send(0x201, struct.pack("<Hi", 0x0F, target))
        wire.send(0x080)
    position = struct.unpack_from("<i", wire.read(0x6064), 4)[0]
    assert abs(position - target) < 100  # within 0.035 deg
    assert wire.node.plant.position_deg == pytest.approx(22.5, abs=0.05)


def test_disturbance_object_pushes_the_axis(wire):
    enable(wire)
    wire.write(0x2003, 0, -200, "<h")
    for _ in range(200):
        wire.send(0x201, struct.pack("<Hh", 0x0F, 0))
        wire.send(0x080)
    assert wire.node.plant.velocity_deg_s == pytest.approx(-2.83 * 200 * 0.1, rel=0.05)


def test_on_its_own_clock_the_next_sync_is_expected_on_the_grid_of_the_communication_cycle():
    node, period = DriveNode(DriveEmulatorConfig(), send=lambda frames: None, clock="wall"), \
        500_000
    node.boot()
    assert node.next_sync_ns(time.monotonic_ns()) is None  # no SYNC yet: nothing to poll for
    node.handle_frame(0x601, struct.pack("<BHBI", 0x23, 0x1006, 0, 500))  # the cycle [us]
    node.handle_frame(0x080, b"")
    last = node._sync_last_ns  # when that SYNC came, on the node's clock
    assert node.next_sync_ns(last + 100_000) == last + period
    assert node.next_sync_ns(last + 700_000) == last + period  # late, still awaited
    assert node.next_sync_ns(last + 800_000) == last + 2 * period  # given up: the next slot
    assert node.next_sync_ns(last + 1_300_000) == last + 3 * period
    assert node.next_sync_ns(last + 101 * period) is None  # the SYNCs stopped
    node.handle_frame(0x601, struct.pack("<BHBI", 0x23, 0x1006, 0, 0))  # no cycle configured
    assert node.next_sync_ns(last + 100_000) is None


def test_on_a_lockstep_masters_time_the_next_sync_is_due_as_soon_as_a_frame_came(wire):
    node = wire.node  # on the master's time: SYNCs come as fast as the master ticks
    # as on a quiet machine (under the suite this one is contended, and no wait polls there)
    node._sync_poll = PollBudget(LOCKSTEP_POLL_NS, contended=lambda: False)
    wire.send(0x080)
    now = time.monotonic_ns()
    assert node.next_sync_ns(now) == now  # polled for at once...
    assert node.next_sync_ns(now + 150_000) == now + 150_000
    assert node.next_sync_ns(now + LOCKSTEP_POLL_NS) is None  # ...for a while, then waited for
    wire.send(0x080)
    now = time.monotonic_ns()
    assert node.next_sync_ns(now) == now
    assert node.next_sync_ns(now + 250_000) is None  # off the CPU for a while: it blocks


def test_a_long_lockstep_run_keeps_no_frame_anywhere_it_is_not_read():
    """Every frame on the lockstep channel is read by the side it is for; the time bus only
    sends SYNCs and keeps no inbox, so nothing piles up over a long run (memory stays flat)."""
    from hil.servo.rig import open_drive

    master = open_drive("emulated", None)
    master.start()
    for _ in range(2000):
        master.exchange(5.0)
    inboxes = master.emulator.channel.inboxes
    assert len(inboxes) == 2  # the node's and the master's
    # the node's is empty; the master's holds at most what came after the last TPDO pair
    # (a heartbeat), taken before the next SYNC
    assert len(inboxes[0]) == 0 and len(inboxes[1]) <= 2
    master.close()


def test_a_batch_of_frames_is_handled_frame_by_frame_and_says_when_the_time_service_ran():
    """A lockstep runner hands a node everything one transmission brought in one call: the
    same as each frame alone, another node's PDO ignored, and True when the last frame was a
    SYNC on the master's time (its time service ran then: the runner need not run it again)."""
    drive = LockstepDrive(node_ids=[1, 2])
    node = drive.nodes[0]
    assert node.handle_frames([(0x000, bytes([0x01, 0]))]) is False  # NMT start: no SYNC
    assert node.handle_frames([(0x080, b""), (0x182, bytes(6))]) is True  # node 2's TPDO
    assert node.sync_count == 1
    read = struct.pack("<BHB", 0x40, 0x6041, 0) + bytes(4)
    assert node.handle_frames([(0x080, b""), (0x601, read)]) is False  # a request after it
    assert node.sync_count == 2
    drive.close()


def test_a_lockstep_node_runs_its_time_service_once_for_each_moment_of_its_time(monkeypatch):
    """Three drives cycled together: a node's time service runs after each SYNC (its time
    moved), and again only once a frame came since; never twice in a row at one node time,
    which would only repeat what it just did."""
    from hil.drivers.canopen import CanDriveMaster, CanLink, DriveMasterConfig
    from hil.drivers.canopen.axes import AxisBus, AxisGroup

    service, dispatch = DriveNode._service, DriveNode._dispatch
    last: dict[int, int | None] = {}  # node id -> the node time of its last service, if no
    repeats = []                      # frame came since

    def counted_service(node, now):
        if last.get(node.node_id) == now:
            repeats.append((node.node_id, now))
        last[node.node_id] = now
        service(node, now)

    def counted_dispatch(node, can_id, data):
        last[node.node_id] = None
        dispatch(node, can_id, data)

    monkeypatch.setattr(DriveNode, "_service", counted_service)
    monkeypatch.setattr(DriveNode, "_dispatch", counted_dispatch)
    ids = [1, 2, 3]
    drive = LockstepDrive(node_ids=ids)
    bus = AxisBus(CanLink(drive.master_bus), ids)
    group = AxisGroup(bus, [CanDriveMaster(bus.node_link(n), DriveMasterConfig(node_id=n),
                                           clock=drive) for n in ids])
    group.start()
    for _ in range(400):  # 0.2 s: the master's and the drives' heartbeats come in it too
        group.send_currents([10.0, -10.0, 5.0])
        assert all(feedback.fresh for feedback in group.receive())
    group.close()
    drive.close()
    assert all(node.sync_count >= 400 for node in drive.nodes)
    assert repeats == []
