"""The in-process channel's acceptance filters: a filtered bus takes only the COB-IDs it
accepts, routes follow a filter that changes, and lockstep drives on filtered buses give
the master, frame for frame, what they gave it when each heard everything."""

import math
import struct

from hil.drivers.canopen import CanDriveMaster, CanLink, DriveMasterConfig
from hil.drivers.canopen.axes import AxisBus, AxisGroup
from hil.emulators.direct_bus import DirectBus, DirectChannel
from hil.emulators.drive.runners import LockstepDrive


def test_a_filtered_bus_takes_what_it_accepts_and_follows_a_changed_filter():
    channel = DirectChannel()
    master, node, observer = channel.attach(), channel.attach(), channel.attach()
    accepted = {0x201, 0x080}
    node.accept(accepted.__contains__)
    master.send_frames([(0x201, b"\x0f\x00"), (0x202, b"\x06\x00"), (0x080, b"")])
    assert node.take_frames() == [(0x201, b"\x0f\x00"), (0x080, b"")]
    assert observer.take_frames() == [(0x201, b"\x0f\x00"), (0x202, b"\x06\x00"), (0x080, b"")]
    accepted.add(0x202)
    channel.refilter()  # the filter's owner tells the channel
    master.send_frames([(0x202, b"\x07\x00")])
    assert node.take_frames() == observer.take_frames() == [(0x202, b"\x07\x00")]
    node.send_frames([(0x181, b"\x27\x02")])  # what a filtered bus sends reaches every other
    assert master.take_frames() == observer.take_frames() == [(0x181, b"\x27\x02")]
    assert channel.carried_frames() and not channel.carried_frames()
    for bus in (master, node, observer):
        bus.shutdown()
    assert channel.inboxes == [] and channel.buses == [] and not channel.filtered


def _wire(filtered: bool, remap: bool, monkeypatch) -> tuple[list, list]:
    """Every frame on the wire of a 3-drive lockstep run, and each node's state at the end;
    ``remap``: drive 3's RPDO 1 moved to drive 2's COB-ID mid-run (then it follows what the
    master sends drive 2)."""
    with monkeypatch.context() as patch:
        if not filtered:
            patch.setattr(DirectBus, "accept", lambda _bus, _accepts: None)
        ids = [1, 2, 3]
        drive = LockstepDrive(node_ids=ids)
        assert drive.channel.filtered == filtered
        observer = drive.attach_bus()
        bus = AxisBus(CanLink(drive.master_bus), ids)
        group = AxisGroup(bus, [CanDriveMaster(bus.node_link(n), DriveMasterConfig(node_id=n),
                                               clock=drive) for n in ids])
        group.start()
        for k in range(300):
            if remap and k == 100:
                node = drive.nodes[2]
                cob_id = node.upload(0x1400, 1)
                node.download(0x1400, 1, struct.pack("<I", int.from_bytes(cob_id, "little")
                                                     | 0x8000_0000))
                node.download(0x1400, 1, struct.pack("<I", 0x202))
            group.send_currents([50.0 * math.sin(k / 20), -20.0, 5.0 + k / 10])
            group.receive()
        wire = observer.take_frames()
        states = [(n.sync_count, n.state, n.plant.position_deg, n.internal_errors,
                   dict(n.objects.values)) for n in drive.nodes]
        group.close()
        drive.close()
    return wire, states


def test_lockstep_drives_on_filtered_buses_put_on_the_wire_what_unfiltered_ones_did(
        monkeypatch):
    for remap in (False, True):
        wire, states = _wire(True, remap, monkeypatch)
        assert (wire, states) == _wire(False, remap, monkeypatch)
        torques = [values[(0x6071, 0)] for *_, values in states]  # target torque
        assert (torques[2] == torques[1]) == remap  # drive 3 took drive 2's set points
