"""The emulated drive's SDO server, frame by frame (CiA 301 7.2.4), against a dictionary of
three objects; canopen's own client talks to the whole node in test_canopen_master.py."""

import struct

import pytest

from hil.emulators.drive.sdo import SdoServer
from hil.protocols.cia301 import (
    ABORT_COMMAND,
    ABORT_NO_OBJECT,
    ABORT_READ_ONLY,
    ABORT_TOGGLE,
    SDO_ABORT,
    SdoAbortError,
)


class Objects:
    def __init__(self):
        self.values = {(0x1008, 0): b"hil drive 0123", (0x6071, 0): b"\x10\x00",
                       (0x1000, 0): b"\x92\x01\x02\x00"}
        self.answers = []
        self.server = SdoServer(self.read, self.write, self.answers.append)

    def read(self, index, subindex):
        if (index, subindex) not in self.values:
            raise SdoAbortError(ABORT_NO_OBJECT)
        return self.values[(index, subindex)]

    def write(self, index, subindex, data):
        if (index, subindex) == (0x1000, 0):
            raise SdoAbortError(ABORT_READ_ONLY)
        self.values[(index, subindex)] = data

    def ask(self, data):
        self.server.handle(bytes(data))
        return self.answers.pop()


def abort_code(answer):
    assert answer[0] == SDO_ABORT
    return struct.unpack_from("<HBL", answer, 1)


def test_expedited_upload_gives_the_size_and_the_bytes():
    objects = Objects()
    answer = objects.ask(struct.pack("<BHB4x", 0x40, 0x6071, 0))
    assert answer[0] == 0x4B and answer[1:4] == b"\x71\x60\x00"  # expedited, n = 2 unused
    assert answer[4:6] == b"\x10\x00"


def test_segmented_upload_sends_seven_bytes_a_segment_with_alternating_toggle():
    objects = Objects()
    answer = objects.ask(struct.pack("<BHB4x", 0x40, 0x1008, 0))
    assert answer[0] == 0x41 and struct.unpack_from("<L", answer, 4)[0] == 14
    first = objects.ask(bytes([0x60]) + bytes(7))
    second = objects.ask(bytes([0x70]) + bytes(7))
    assert first[0] == 0x00 and first[1:8] == b"hil dri"
    assert second[0] == 0x11 and second[1:8] == b"ve 0123"  # toggle, last segment
    assert abort_code(objects.ask(bytes([0x60]) + bytes(7)))[2] == ABORT_COMMAND  # no transfer


def test_a_segment_with_the_wrong_toggle_is_aborted():
    objects = Objects()
    objects.ask(struct.pack("<BHB4x", 0x40, 0x1008, 0))
    assert abort_code(objects.ask(bytes([0x70]) + bytes(7))) == (0x1008, 0, ABORT_TOGGLE)


def test_expedited_and_segmented_downloads_write_the_object():
    objects = Objects()
    assert objects.ask(struct.pack("<BHB2sxx", 0x2B, 0x6071, 0, b"\x20\x00"))[0] == 0x60
    assert objects.values[(0x6071, 0)] == b"\x20\x00"
    assert objects.ask(struct.pack("<BHBL", 0x21, 0x6071, 0, 2))[0] == 0x60
    assert objects.ask(bytes([0x0B, 0x30, 0x00]) + bytes(5))[0] == 0x20  # 2 bytes, last
    assert objects.values[(0x6071, 0)] == b"\x30\x00"


@pytest.mark.parametrize("request_, expected", [
    (struct.pack("<BHB4x", 0x40, 0x2222, 0), (0x2222, 0, ABORT_NO_OBJECT)),
    (struct.pack("<BHBL", 0x23, 0x1000, 0, 1), (0x1000, 0, ABORT_READ_ONLY)),
    (struct.pack("<BHB4x", 0xC0, 0x6071, 0), (0x6071, 0, ABORT_COMMAND)),   # block download
    (struct.pack("<BHB4x", 0xE0, 0x6071, 0), (0x6071, 0, ABORT_COMMAND)),   # no such command
    (struct.pack("<BHB", 0x40, 0x6071, 0), (0x6071, 0, ABORT_COMMAND)),     # 4 bytes, not 8
])
def test_refused_requests_are_aborted_with_the_object_and_the_cia301_code(request_, expected):
    assert abort_code(Objects().ask(request_)) == expected


def test_a_client_abort_ends_the_transfer_without_an_answer():
    objects = Objects()
    objects.ask(struct.pack("<BHB4x", 0x40, 0x1008, 0))
    objects.server.handle(struct.pack("<BHBL", 0x80, 0x1008, 0, ABORT_COMMAND))
    assert objects.answers == []
    assert abort_code(objects.ask(bytes([0x60]) + bytes(7)))[2] == ABORT_COMMAND
