"""canopen's own CiA 402 master (``BaseNode402``) on a node of hil's drive emulator: a master
hil did not write, for tests that drive the emulator as any CANopen tool would."""

from __future__ import annotations

import canopen

from hil.emulators.drive.od import build_object_dictionary

CANOPEN_TIMEOUTS = ("TIMEOUT_SWITCH_STATE_FINAL", "TIMEOUT_SWITCH_STATE_SINGLE",
                    "TIMEOUT_CHECK_TPDO", "TIMEOUT_SWITCH_OP_MODE")


def add_402_node(network: canopen.Network, node_id: int = 1, *,
                 sdo_timeout_s: float = 3.0) -> canopen.BaseNode402:
    """Node ``node_id`` added to ``network`` with the emulator's dictionary and patient
    time-outs (a loaded test machine), taken to PRE-OPERATIONAL with its PDO maps read."""
    node = canopen.BaseNode402(node_id, build_object_dictionary(node_id))
    for name in CANOPEN_TIMEOUTS:
        setattr(node, name, 5.0)
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
    node.nmt.state = "PRE-OPERATIONAL"
    node.setup_402_state_machine(read_pdos=True)
    return node
