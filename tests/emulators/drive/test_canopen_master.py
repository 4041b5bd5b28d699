"""An independent master: canopen's BaseNode402 (through python-can) drives the emulator.

The emulator runs in real time on a python-can virtual bus (a BusRunner thread); canopen
reads the PDO configuration by SDO, starts SYNC and RPDO1 itself, and walks the state machine
with its own code. Timeouts are generous: the box may be loaded."""

import uuid

import can
import canopen
import pytest

from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.node import DriveNode
from hil.emulators.drive.runners import BusRunner, bus_sender
from hil.emulators.drive.switches import Switches
from tests.canopen_peer import add_402_node

Homing, State402 = canopen.profiles.p402.Homing, canopen.profiles.p402.State402


def walk_to_operation_enabled(network: canopen.Network) -> canopen.BaseNode402:
    """The canopen way: PRE-OP, read PDO maps, OPERATIONAL, SYNC + RPDO, mode, state."""
    node = add_402_node(network, 1, sdo_timeout_s=2.0)
    assert node.tpdo[1].cob_id == 0x181 and node.rpdo[1].cob_id == 0x201
    assert [v.index for v in node.tpdo[1]] == [0x6041, 0x6064]
    node.nmt.state = "OPERATIONAL"
    network.sync.start(0.005)
    node.rpdo[1].start(0.005)
    node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
    assert node.sdo[0x6061].raw == 10
    node.state = "OPERATION ENABLED"
    return node


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_base_node_402_enables_the_emulator_and_reads_statusword_and_position():
    channel = f"canopen-master-{uuid.uuid4().hex}"
    node_bus = can.Bus(interface="virtual", channel=channel)
    emulated = DriveNode(DriveEmulatorConfig(sync_loss_timeout_ms=5000),
                         send=bus_sender(node_bus))
    runner = BusRunner(emulated, node_bus).start()
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    try:
        node = walk_to_operation_enabled(network)
        assert node.state == "OPERATION ENABLED"
        statusword = node.sdo[0x6041].raw
        mask, value = canopen.profiles.p402.State402.SW_MASK["OPERATION ENABLED"]
        assert statusword & mask == value
        assert node.sdo[0x6064].raw == emulated.plant.position_increments()
        # a torque command through canopen's periodic RPDO moves the axis
        node.rpdo[1]["Target torque"].raw = 200
        node.tpdo[1].wait_for_reception(5.0)
        for _ in range(20):
            node.tpdo[1].wait_for_reception(5.0)
        assert node.tpdo_values[0x6064] == pytest.approx(emulated.plant.position_increments(),
                                                          abs=20_000)
        assert emulated.plant.velocity_deg_s > 0
        node.state = "SWITCH ON DISABLED"
        assert node.sdo[0x6041].raw & 0x4F == 0x40
    finally:
        network.sync.stop()
        network.disconnect()
        runner.stop()
        node_bus.shutdown()


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_base_node_402_homes_the_emulator_through_its_pdos():
    """canopen's BaseNode402 homes it as its ``homing()`` does (its mode switch, the start
    bit in its periodic RPDO, the statusword from its TPDO read as ``Homing.STATES``) on
    method 34 with the index pulse 2 deg ahead. Not ``homing()`` itself: it takes the
    statusword of one cycle after the start for an answer, and a drive that has not latched
    the start yet rightly says "not started" (bit 10 alone), which it reads as interrupted."""
    channel = f"canopen-homing-{uuid.uuid4().hex}"
    node_bus = can.Bus(interface="virtual", channel=channel)
    config = DriveEmulatorConfig(sync_loss_timeout_ms=5000,
                                 switches=Switches(index_pulse_deg=2.0))
    emulated = DriveNode(config, send=bus_sender(node_bus))
    runner = BusRunner(emulated, node_bus).start()
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    try:
        node = walk_to_operation_enabled(network)
        node.sdo[0x6098].raw = 34
        node.sdo[0x607C].raw = 1000
        node.op_mode = "HOMING"
        assert node.op_mode == "HOMING"
        node.controlword = State402.CW_OPERATION_ENABLED | Homing.CW_START
        status = ""
        for _ in range(3000):  # 15 s of 5 ms cycles at most
            node.check_statusword()
            status = next(key for key, (mask, bits) in Homing.STATES.items()
                          if node.statusword & mask == bits)
            if status == "TARGET REACHED":
                break
        assert status == "TARGET REACHED"  # homing attained, standing at home
        assert abs(node.sdo[0x6064].raw - 1000) <= node.sdo[0x6067].raw
        assert emulated.plant.position_deg == pytest.approx(2.0, abs=0.1)
    finally:
        network.sync.stop()
        network.disconnect()
        runner.stop()
        node_bus.shutdown()
