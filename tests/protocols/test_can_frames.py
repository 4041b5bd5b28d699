"""Frames as (id, data) tuples: the adapter over any python-can bus (a real ``virtual`` bus
pair here) and the in-process lockstep channel carry the same frames in the same order."""

import uuid

import can

from hil.emulators.direct_bus import DirectChannel
from hil.protocols.can_frames import FrameBus, MessageFrames, frames_of


def virtual_pair():
    channel = f"frames-{uuid.uuid4().hex}"
    return (can.Bus(interface="virtual", channel=channel),
            can.Bus(interface="virtual", channel=channel))


def test_a_python_can_bus_gets_an_adapter_that_drops_what_cia_301_never_sends():
    sender, receiver = virtual_pair()
    try:
        frames = frames_of(receiver)
        assert isinstance(frames, MessageFrames)
        for msg in (can.Message(arbitration_id=0x181, is_error_frame=True),
                    can.Message(arbitration_id=0x1ABCDEF0, data=b"\x01", is_extended_id=True),
                    can.Message(arbitration_id=0x181, is_remote_frame=True, dlc=2,
                                is_extended_id=False),
                    can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False)):
            sender.send(msg)
        assert frames.recv_frame(1.0) == (0x181, b"\x01\x02")
        assert frames.recv_frame(0) is None
        frames_of(sender).send_frames([(0x80, b""), (0x201, b"\x0f\x00")])
        first, second = receiver.recv(1.0), receiver.recv(1.0)
        assert (first.arbitration_id, first.dlc, first.is_extended_id) == (0x80, 0, False)
        assert (second.arbitration_id, bytes(second.data)) == (0x201, b"\x0f\x00")
    finally:
        sender.shutdown()
        receiver.shutdown()


def test_the_direct_channel_carries_tuples_and_python_can_messages_alike():
    channel = DirectChannel()
    master, node, observer = channel.attach(), channel.attach(), channel.attach()
    assert frames_of(master) is master and isinstance(master, FrameBus)
    master.send_frames([(0x201, b"\x0f\x00"), (0x80, b"")])
    assert [node.recv_frame(), node.recv_frame(), node.recv_frame()] == \
        [(0x201, b"\x0f\x00"), (0x80, b""), None]
    seen = [observer.recv(0), observer.recv(0)]  # an observer reads python-can messages
    assert [(m.arbitration_id, bytes(m.data)) for m in seen] == [(0x201, b"\x0f\x00"), (0x80, b"")]
    assert master.recv_frame() is None  # a bus never hears itself
    observer.send(can.Message(arbitration_id=0x1ABCDEF0, is_extended_id=True))  # not CiA 301
    observer.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
    assert node.recv_frame() == (0x701, b"\x05") and node.recv_frame() is None
    for bus in (master, node, observer):
        bus.shutdown()


def test_a_direct_bus_hands_over_every_frame_waiting_at_once():
    channel = DirectChannel()
    master, node = channel.attach(), channel.attach()
    master.send_frames([(0x201, b"\x0f\x00"), (0x80, b"")])
    master.send_frames([(0x701, b"\x05")])
    assert node.take_frames() == [(0x201, b"\x0f\x00"), (0x80, b""), (0x701, b"\x05")]
    assert node.take_frames() == [] and node.recv_frame() is None  # none left waiting
    for bus in (master, node):
        bus.shutdown()


def test_a_bus_shut_down_leaves_every_other_bus_of_the_channel_hearing():
    """Inboxes are told apart by identity: two empty ones are equal deques, and shutting one
    bus down once detached the first empty inbox of the channel, another bus's."""
    channel = DirectChannel()
    node, master, observer = channel.attach(), channel.attach(), channel.attach()
    observer.shutdown()  # every inbox empty: equal to the node's and the master's
    master.send_frames([(0x80, b"")])
    assert node.recv_frame() == (0x80, b"")
    node.send_frames([(0x181, b"\x27\x02")])
    assert master.recv_frame() == (0x181, b"\x27\x02")
    assert len(channel.inboxes) == 2
    for bus in (master, node):
        bus.shutdown()
    assert channel.inboxes == []
