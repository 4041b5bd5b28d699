"""The emulated drive's object dictionary as an EDS file (CiA 306), for any node id.

A value that follows the node id (the COB-IDs of EMCY 0x1014, the SDO server 0x1200, the PDOs
0x1400.. / 0x1800.., the serial number) is written relative to it, ``$NODEID+0x180``, as
CiA 306 has it: found by building the dictionary at two node ids and keeping each value that
moves with the id, not from a list that could miss one. ``canopen.import_od(path, node_id)``
then gives every node its own COB-IDs.
"""

from __future__ import annotations

from canopen import export_od
from canopen.objectdictionary import ObjectDictionary

from hil.emulators.drive.od import DEVICE_NAME, OdDefaults, build_object_dictionary, iter_variables
from hil.protocols.cia301 import IDENTITY

# The bit rates the EDS claims: every classic CAN rate of CiA 301 (10 to 1000 kbit/s). The
# emulator has no bit timing of its own: it takes and gives whole frames over socketcand's
# TCP, and a socketcand gateway (or SocketCAN below it) sets the rate on its interface, not on
# the node. So it stands behind a bus at any of these rates; whether a cycle fits the rate is
# the master's question (`hil drive plan`), not the node's.
BIT_RATES = (10_000, 20_000, 50_000, 125_000, 250_000, 500_000, 800_000, 1_000_000)


def node_relative(od: ObjectDictionary, node_id: int, defaults: OdDefaults | None = None
                  ) -> int:
    """Mark every default of ``od`` (the dictionary of node ``node_id``) that follows the node
    id as ``$NODEID+offset``; the number of values marked."""
    other_id = node_id + 2 if node_id <= 125 else node_id - 2
    other = {(v.index, v.subindex): v.default
             for v in iter_variables(build_object_dictionary(other_id, defaults))}
    marked = 0
    for var in iter_variables(od):
        moved = other[(var.index, var.subindex)]
        if isinstance(var.default, int) and isinstance(moved, int) and moved != var.default:
            if moved - var.default != other_id - node_id:
                raise ValueError(f"0x{var.index:04X}:{var.subindex} changes with the node id "
                                 "but is not the node id plus a constant")
            var.default_raw = f"$NODEID+0x{var.default - node_id:X}"
            marked += 1
    return marked


def emulator_eds(node_id: int, defaults: OdDefaults | None = None) -> ObjectDictionary:
    """The emulator's dictionary ready to export: node-relative values, its bit rates, the
    device information of its identity object (0x1018)."""
    od = build_object_dictionary(node_id, defaults)
    node_relative(od, node_id, defaults)
    identity = {var.subindex: var.default for var in iter_variables(od)
                if var.index == IDENTITY}
    info = od.device_information
    info.vendor_name = "hil"
    info.product_name = DEVICE_NAME
    info.vendor_number = identity[1]
    info.product_number = identity[2]
    info.revision_number = identity[3]
    info.allowed_baudrates = set(BIT_RATES)
    return od


def write_eds(path: str, node_id: int, defaults: OdDefaults | None = None) -> None:
    """The emulator's EDS at ``path`` (OSError when it cannot be written)."""
    export_od(emulator_eds(node_id, defaults), path, doc_type="eds")
