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
from tests.canopen_peer import add_402_node


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
