"""The slave's CoE SDO server, mailbox message by message, against a dictionary of three
objects and a small mailbox (so a 40-byte object needs segments both ways)."""

import struct

import pytest

from hil.emulators.ethercat.coe import CoeServer, coe
from hil.protocols.cia301 import ABORT_NO_OBJECT, ABORT_READ_ONLY, ABORT_TOGGLE, SdoAbortError

NAME = b"a drive name that needs several segments"  # 40 bytes
MAILBOX = 24  # 8 header bytes: an initiate carries 8 data bytes, a segment 15


class Objects:
    def __init__(self):
        self.values = {(0x1008, 0): NAME, (0x6071, 0): b"\x10\x00", (0x1000, 0): b"\x92\x01"}
        self.server = CoeServer(self.read, self.write, MAILBOX)

    def read(self, index, subindex):
        if (index, subindex) not in self.values:
            raise SdoAbortError(ABORT_NO_OBJECT)
        return self.values[(index, subindex)]

    def write(self, index, subindex, data):
        if index == 0x1000:
            raise SdoAbortError(ABORT_READ_ONLY)
        self.values[(index, subindex)] = data

    def ask(self, sdo: bytes) -> bytes:
        (answer,) = self.server.handle(coe(2, sdo))
        length, _, _, kind = struct.unpack_from("<HHBB", answer)
        service = struct.unpack_from("<H", answer, 6)[0] >> 12
        # an answer is an SDO response; an abort an "abort SDO transfer request" (ETG.1000.6)
        assert kind & 0x0F == 3 and service == (2 if answer[8] == 0x80 else 3)
        return answer[8:6 + length]


def test_small_objects_go_expedited_both_ways():
    objects = Objects()
    assert objects.ask(struct.pack("<BHB", 0x40, 0x6071, 0) + bytes(4)) == \
        struct.pack("<BHB", 0x4B, 0x6071, 0) + b"\x10\x00\x00\x00"
    assert objects.ask(struct.pack("<BHB", 0x2B, 0x6071, 0) + b"\x20\x00\x00\x00")[0] == 0x60
    assert objects.values[(0x6071, 0)] == b"\x20\x00"


def test_a_long_object_is_uploaded_in_segments_with_the_toggle():
    objects = Objects()
    first = objects.ask(struct.pack("<BHB", 0x40, 0x1008, 0) + bytes(4))
    assert first[0] == 0x41 and struct.unpack_from("<I", first, 4)[0] == len(NAME)
    data, toggle = bytearray(first[8:]), 0
    while True:
        segment = objects.ask(bytes([0x60 | toggle]) + bytes(7))
        assert segment[0] & 0xE0 == 0 and segment[0] & 0x10 == toggle
        data += segment[1:]
        if segment[0] & 0x01:
            break
        toggle ^= 0x10
    assert bytes(data) == NAME
    # a segment out of turn is refused with the CiA 301 code
    objects.ask(struct.pack("<BHB", 0x40, 0x1008, 0) + bytes(4))
    assert objects.ask(bytes([0x70]) + bytes(7))[0] == 0x80


def test_a_long_download_in_segments_and_the_aborts():
    objects = Objects()
    text = b"x" * 30
    start = objects.ask(struct.pack("<BHBI", 0x21, 0x1008, 0, len(text)) + text[:8])
    assert start[0] == 0x60
    assert objects.ask(bytes([0x00]) + text[8:23])[0] == 0x20
    assert objects.ask(bytes([0x11]) + text[23:])[0] == 0x30
    assert objects.values[(0x1008, 0)] == text
    refused = objects.ask(struct.pack("<BHB", 0x2B, 0x1000, 0) + bytes(4))
    assert refused[0] == 0x80 and struct.unpack_from("<I", refused, 4)[0] == ABORT_READ_ONLY
    missing = objects.ask(struct.pack("<BHB", 0x40, 0x7777, 0) + bytes(4))
    assert struct.unpack_from("<I", missing, 4)[0] == ABORT_NO_OBJECT
    assert struct.unpack_from("<I", objects.ask(bytes([0x10]) + bytes(7)), 4)[0] != \
        ABORT_TOGGLE  # no download under way: the command itself is refused


@pytest.mark.parametrize("kind", [0x01, 0x04])  # AoE, FoE: not served
def test_another_protocol_gets_a_mailbox_error(kind):
    objects = Objects()
    (answer,) = objects.server.handle(struct.pack("<HHBB", 2, 0, 0, kind) + b"\0\0")
    assert answer[5] & 0x0F == 0 and struct.unpack_from("<HH", answer, 6) == (1, 2)
