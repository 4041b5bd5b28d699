"""The drive tests again, over socketcand to a separate emulator process (``hil emulate drive``)
on 127.0.0.1: the master reaches it with python-can's stock ``socketcand`` interface, exactly as
it would reach a socketcand gateway in front of a real drive. Bounded: four emulator processes,
generous time-outs, no timing figure asserted beyond "not before the configured time-out"."""

import math
import signal
import socket
import struct
import time
from pathlib import Path

import can
import canopen
import pytest
from canopen.profiles.p402 import State402

from hil.contracts import no_event
from hil.drivers.canopen import DriveFaultError, DriveLinkLostError
from hil.protocols import cia402
from hil.protocols.cia402 import state_of
from hil.servo.config import load_drive_config
from hil.servo.rig import open_drive
from tests.canopen_peer import add_402_node
from tests.drive_processes import start_drive_emulator, stop_drive_emulator
from tests.served_here import drive_served_here

REPO = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]

MASTER = {  # generous for a loaded box; the fault tests shorten what they test
    "rx_timeout_us": 500_000, "sdo_timeout_ms": 3000, "state_timeout_ms": 5000,
    "heartbeat_timeout_ms": 5000, "stale_cycles": 20,
}


def start_emulator(tmp_path, name, port=0, **emulator):
    config = tmp_path / f"{name}.toml"
    config.write_text("[emulator]\n" + "".join(f"{k} = {v}\n" for k, v in emulator.items()))
    return start_drive_emulator(config, port)


def master_for(port, events=None, **overrides):
    config = load_drive_config(overrides={"master": {**MASTER, **overrides}})
    return open_drive(f"socketcand://127.0.0.1:{port}", config, on_event=events or no_event)


@pytest.fixture(scope="module")
def emulator(tmp_path_factory):
    proc, port = start_emulator(tmp_path_factory.mktemp("drive"), "relaxed",
                                sync_loss_timeout_ms=5000)
    yield port
    stop_drive_emulator(proc)


SHUTDOWN, SWITCH_ON, ENABLE = cia402.CW_SHUTDOWN, cia402.CW_SWITCH_ON, cia402.CW_ENABLE_OPERATION
DISABLE_VOLTAGE, QUICK_STOP = cia402.CW_DISABLE_VOLTAGE, cia402.CW_QUICK_STOP
SOD, RTSO, SO, OE, QSA = (cia402.SWITCH_ON_DISABLED, cia402.READY_TO_SWITCH_ON,
                          cia402.SWITCHED_ON, cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE)
CHART = [  # (controlword, state after the SYNC): every transition, as in the lockstep test
    (DISABLE_VOLTAGE, SOD), (SHUTDOWN, RTSO), (SWITCH_ON, SO), (ENABLE, OE), (SWITCH_ON, SO),
    (SHUTDOWN, RTSO), (DISABLE_VOLTAGE, SOD), (SHUTDOWN, RTSO), (QUICK_STOP, SOD),
    (SHUTDOWN, RTSO), (SWITCH_ON, SO), (DISABLE_VOLTAGE, SOD), (SHUTDOWN, RTSO), (SWITCH_ON, SO),
    (QUICK_STOP, SOD), (SHUTDOWN, RTSO), (ENABLE, OE), (SHUTDOWN, RTSO), (SWITCH_ON, SO),
    (ENABLE, OE), (QUICK_STOP, QSA), (ENABLE, OE), (QUICK_STOP, QSA), (DISABLE_VOLTAGE, SOD),
]


def test_every_transition_of_the_chart_over_socketcand(emulator):
    master = master_for(emulator, quick_stop_option=5)
    try:
        master.start()
        for step, (controlword, state) in enumerate(CHART):
            feedback = master.cycle(controlword)
            mask, value = State402.SW_MASK[state]
            assert feedback.fresh and feedback.statusword & mask == value, (step, state)
            assert state_of(master.sdo.read_int(0x6041, 0, "<H")) == state
        master.start()
        master.exchange(0.0)
        for _ in range(200):  # fault: over-current trips the drive; reset by bit 7
            feedback = master.cycle(ENABLE, 16000)
            if feedback.state == cia402.FAULT:
                break
        assert feedback.state == cia402.FAULT
        assert master.cycle(cia402.CW_FAULT_RESET).state == SOD
    finally:
        master.close()


def test_base_node_402_over_socketcand(emulator):
    network = canopen.Network()
    network.connect(interface="socketcand", host="127.0.0.1", port=emulator, channel="can0")
    try:
        node = add_402_node(network, 1)
        node.nmt.state = "OPERATIONAL"
        network.sync.start(0.005)
        node.rpdo[1].start(0.005)
        node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
        node.state = "OPERATION ENABLED"
        statusword = node.sdo[0x6041].raw
        assert state_of(statusword) == "OPERATION ENABLED"
        position = node.sdo[0x6064].raw
        assert 0 <= position < 1 << 20
        node.tpdo[1].wait_for_reception(5.0)
        assert state_of(node.tpdo_values[0x6041]) == "OPERATION ENABLED"
        node.state = "SWITCH ON DISABLED"
    finally:
        network.sync.stop()
        network.disconnect()


def test_open_loop_physics_over_socketcand(emulator):
    master = master_for(emulator)
    try:
        start = master.start()
        cycles, current = 1000, 200.0
        for _ in range(cycles):
            feedback = master.exchange(current)
        assert feedback.fresh
        t = cycles * 500e-6
        moved = feedback.position_deg - start.position_deg - start.velocity_deg_s * t
        assert 2.0 * moved / t**2 / current == pytest.approx(2.83, rel=0.02)
        assert master.stats.stale == 0
    finally:
        master.close()


def test_a_bus_name_the_gateway_does_not_serve_is_one_clear_error(emulator):
    with pytest.raises(DriveLinkLostError, match=r"bus 'can9'.*could not open bus"):
        open_drive(f"socketcand://127.0.0.1:{emulator}/can9")


def test_an_address_nobody_listens_on_is_one_clear_error():
    with socket.socket() as probe:  # a port that was free a moment ago
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with pytest.raises(DriveLinkLostError, match=f"cannot connect to socketcand at "
                                                 f"127.0.0.1:{port}"):
        open_drive(f"socketcand://127.0.0.1:{port}/can0")


def emcy_listener(port):
    return can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="can0",
                   can_filters=[{"can_id": 0x81, "can_mask": 0x7FF}])


def wait_emcy(bus, code, timeout_s):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = bus.recv(0.2)
        if msg is not None and struct.unpack_from("<H", msg.data)[0] == code:
            return msg
    return None


def test_sync_loss_then_heartbeat_loss_fault_the_drive_in_time(tmp_path):
    proc, port = start_emulator(tmp_path, "strict", sync_loss_timeout_ms=500)
    listener = emcy_listener(port)
    events = []
    master = master_for(port, lambda kind, message, **kw: events.append((kind, kw)),
                        heartbeat_timeout_ms=3000)
    try:
        master.start()
        for _ in range(49):
            master.exchange(0.0)
        # taken before the last SYNC goes out: the drive's watch starts when it gets it, which a
        # loaded machine may delay past the moment the exchange returns (0.499 s seen)
        last_sync = time.monotonic()
        master.exchange(0.0)  # no more SYNC (nor heartbeat) from here on
        emcy = wait_emcy(listener, 0x8130, 5.0)
        assert emcy is not None, "no EMCY 0x8130 after SYNC stopped"
        assert time.monotonic() - last_sync >= 0.5
        assert emcy.data[3] == 0x02  # cause: SYNC
        with pytest.raises(DriveFaultError, match="0x8130"):
            master.exchange(0.0)
        assert ("drive.emcy", "error") in [(k, kw.get("level")) for k, kw in events]
        master.recover()
        master.close()
        # now the master's heartbeat stops while SYNC goes on: beat every 2 s, drive waits 300 ms
        master = master_for(port, heartbeat_period_ms=2000, heartbeat_timeout_ms=300)
        first_beat = time.monotonic()  # before the first heartbeat goes out, as above
        master.start()
        with pytest.raises(DriveFaultError, match="0x8130"):
            while time.monotonic() - first_beat < 10.0:
                master.exchange(0.0)
        assert time.monotonic() - first_beat >= 0.3
        emcy = wait_emcy(listener, 0x8130, 5.0)
        assert emcy is not None and emcy.data[3] == 0x01  # cause: heartbeat
    finally:
        master.close()
        listener.shutdown()
        stop_drive_emulator(proc)


def test_master_declares_link_lost_when_tpdos_stop(tmp_path):
    proc, port = start_emulator(tmp_path, "frozen", sync_loss_timeout_ms=5000)
    events = []
    master = master_for(port, lambda kind, message, **kw: events.append(kind),
                        rx_timeout_us=50_000, stale_cycles=4)
    try:
        master.start()
        for _ in range(20):
            master.exchange(0.0)
        proc.send_signal(signal.SIGSTOP)  # the drive stops answering, the TCP link stays
        calls = 0
        with pytest.raises(DriveLinkLostError, match="no TPDO for 4 cycles"):
            while calls < 20:
                calls += 1
                master.exchange(0.0)
        assert calls <= 4 and "drive.link_lost" in events
        proc.send_signal(signal.SIGCONT)
        with pytest.raises(DriveLinkLostError, match="latched"):
            master.exchange(0.0)
        assert master.recover().state == "OPERATION ENABLED"
        assert master.exchange(0.0).fresh
    finally:
        proc.send_signal(signal.SIGCONT)
        master.close()
        stop_drive_emulator(proc)


def test_restarted_emulator_is_used_again_only_after_recover(tmp_path):
    proc, port = start_emulator(tmp_path, "first", sync_loss_timeout_ms=5000)
    master = master_for(port, rx_timeout_us=50_000, stale_cycles=4)
    try:
        master.start()
        for _ in range(200):
            feedback = master.exchange(300.0)
        assert feedback.position_deg > 0
        proc.kill()
        proc.wait(10)
        with pytest.raises(DriveLinkLostError):
            for _ in range(20):
                master.exchange(0.0)
        stop_drive_emulator(proc)
        proc, _ = start_emulator(tmp_path, "second", port=port, sync_loss_timeout_ms=5000)
        with pytest.raises(DriveLinkLostError, match="latched"):
            master.exchange(0.0)  # the drive is back, but nobody said so
        feedback = master.recover()  # reconnects, configures, enables
        assert feedback.state == "OPERATION ENABLED"
        assert feedback.velocity_deg_s == 0.0  # a fresh drive: the old motion is gone
        fresh = master.exchange(100.0)
        assert fresh.fresh and math.isfinite(fresh.position_deg)
    finally:
        master.close()
        stop_drive_emulator(proc)


def test_several_drives_on_one_bus_each_move_their_own_axis():
    """What ``hil emulate drive --node 1 --node 2`` serves (here in this process; the command's
    own process drives several axes in tests/integration/test_axes_bus.py): two drives on one
    socketcand bus, driven by canopen's own master (one SYNC for both): each answers as its
    node and moves its axis with its own torque, the other way for node 2."""
    with drive_served_here(node=[1, 2]) as emulator:
        host, port = emulator.url.removeprefix("socketcand://").split(":")
        network = canopen.Network()
        network.connect(interface="socketcand", host=host, port=int(port), channel="can0")
        nodes = {}
        try:
            for node_id, torque in ((1, 300), (2, -300)):
                node = add_402_node(network, node_id)
                assert node.sdo[0x1018][4].raw is not None  # its own SDO server answers
                nodes[node_id] = (node, torque)
            network.sync.start(0.005)
            for node, _ in nodes.values():
                node.nmt.state = "OPERATIONAL"
                node.rpdo[1]["Target torque"].raw = 0
                node.rpdo[1].start(0.005)
                node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
                node.state = "OPERATION ENABLED"
            start = {n: node.sdo[0x6064].raw for n, (node, _) in nodes.items()}
            for node, torque in nodes.values():
                node.rpdo[1]["Target torque"].raw = torque
            deadline, moved = time.monotonic() + 10.0, {1: 0, 2: 0}
            while min(abs(m) for m in moved.values()) < 500 and time.monotonic() < deadline:
                time.sleep(0.05)  # the plant moves one step per SYNC, however slow they come
                moved = {n: (node.sdo[0x6064].raw - start[n] + (1 << 19)) % (1 << 20)
                         - (1 << 19) for n, (node, _) in nodes.items()}
            for node, _ in nodes.values():
                node.rpdo[1]["Target torque"].raw = 0
                node.state = "SWITCH ON DISABLED"
        finally:
            # the periodic tasks (RPDOs, SYNC) stopped and their threads ended before the bus
            # they send on closes: python-can's stop() only asks the thread to end, and one
            # still in its send then writes to a closed socket. canopen's task wraps
            # python-can's (its ``_task``), whose thread is the one to wait for
            tasks = [node.rpdo[1]._task for node, _ in nodes.values()] + [network.sync._task]
            threads = [task._task.thread for task in tasks if task is not None]
            for node, _ in nodes.values():
                node.rpdo[1].stop()
            network.sync.stop()
            for thread in threads:
                thread.join(timeout=5)
                assert not thread.is_alive(), f"{thread.name} still sends after its stop"
            network.disconnect()
    assert moved[1] >= 500 and moved[2] <= -500, moved
