"""What the campaign feeds hil's parsers: hypothesis strategies for Modbus TCP and RTU
frames, CAN frames, socketcand text, and the mutations of a valid file (bytes or text).

Each draws mostly near the valid form (the right function code with a wrong count, an SDO
request for a real object with a wrong size, a config key with a value of another type) and
sometimes anything at all: random bytes alone rarely get past the first check of a parser.
"""

from __future__ import annotations

import itertools
import struct
from dataclasses import dataclass

from hypothesis import strategies as st

from hil.emulators.bench.modbus_server import crc16

# -- Modbus ------------------------------------------------------------------------------
#: the bench's units (relays, meter, levels) mostly, else the clock's or ids no device has
UNITS = st.one_of(*(st.sampled_from([1, 2, 3]) for _ in range(4)),
                  st.sampled_from([0, 4, 247, 248, 255]), st.integers(0, 255))
WORDS = st.one_of(st.integers(0, 16), st.sampled_from([0x00FF, 0x0100, 0x7FFF, 0x8000, 0xFF00,
                                                       0xFFFE, 0xFFFF]), st.integers(0, 0xFFFF))
ADDRESSES = st.one_of(st.integers(0, 10), st.sampled_from([0x12, 0x34, 0x38, 0x46, 0x48, 0x4E,
                                                           0x4F, 0x7E, 0x7F]), WORDS)
COUNTS = st.one_of(st.integers(0, 10), st.sampled_from([76, 80, 81, 125, 126, 2000, 2001,
                                                        0x7B0, 0x7B1]), WORDS)
WRITE_VALUES = st.one_of(st.sampled_from([0xFF00, 0x0000]), WORDS)


def mostly(value: object, other: st.SearchStrategy[object]) -> st.SearchStrategy[object]:
    """``value`` three times in four, else ``other``: a field that is mostly right, so that
    the parser gets past it to the fields behind."""
    return st.one_of(st.just(value), st.just(value), st.just(value), other)


@st.composite
def modbus_pdus(draw: st.DrawFn) -> bytes:
    """A request PDU: a read, a single or multiple write, a device identification, or any
    bytes; then perhaps cut short or followed by junk."""
    kind = draw(st.sampled_from(["read", "write", "write_many", "identify", "any"]))
    if kind == "read":
        code = draw(st.sampled_from([1, 2, 3, 4]) | st.integers(0, 255))
        pdu = struct.pack(">BHH", code, draw(ADDRESSES), draw(COUNTS))
    elif kind == "write":
        pdu = struct.pack(">BHH", draw(st.sampled_from([5, 6])), draw(ADDRESSES),
                          draw(WRITE_VALUES))
    elif kind == "write_many":
        code = draw(st.sampled_from([15, 16]))
        count = draw(COUNTS)
        size = (count + 7) // 8 if code == 15 else 2 * count
        size = draw(st.sampled_from([size, size % 256]) | st.integers(0, 255))
        values = draw(st.binary(min_size=min(size, 246), max_size=min(size, 246)) |
                      st.binary(max_size=250))
        pdu = struct.pack(">BHHB", code, draw(ADDRESSES), count, size % 256) + values
    elif kind == "identify":
        pdu = bytes([0x2B, draw(st.sampled_from([0x0E]) | st.integers(0, 255)),
                     draw(st.integers(0, 5) | st.integers(0, 255)),
                     draw(st.integers(0, 6) | st.integers(0, 255))])
    else:
        pdu = draw(st.binary(min_size=1, max_size=253))
    cut = draw(st.sampled_from([None, None, None, "cut", "junk"]))
    if cut == "cut":
        pdu = pdu[:draw(st.integers(1, max(1, len(pdu) - 1)))]
    elif cut == "junk":
        pdu += draw(st.binary(min_size=1, max_size=8))
    return pdu


@st.composite
def clock_pdus(draw: st.DrawFn) -> bytes:
    """A request to the bench emulator's clock unit: ``TIME`` (FC16 at 0, four words),
    ``CONTROL`` (FC06 at 4), a read (FC03), or any of the Modbus PDUs."""
    kind = draw(st.sampled_from(["time", "control", "read", "other"]))
    if kind == "time":
        t_ns = draw(st.one_of(st.integers(0, 10**10), st.integers(0, 2**64 - 1)))
        words = [(t_ns >> shift) & 0xFFFF for shift in (48, 32, 16, 0)]
        pdu = struct.pack(">BHHB4H", 16, draw(mostly(0, ADDRESSES)), draw(mostly(4, COUNTS)),
                          draw(mostly(8, st.integers(0, 255))), *words)
        if draw(st.integers(0, 3)) == 0:
            pdu = pdu[:draw(st.integers(1, len(pdu)))]
        return pdu
    if kind == "control":
        return struct.pack(">BHH", 6, draw(mostly(4, ADDRESSES)), draw(WORDS))
    if kind == "read":
        return struct.pack(">BHH", 3, draw(ADDRESSES), draw(COUNTS))
    return draw(modbus_pdus())


@dataclass(frozen=True)
class TcpFrame:
    """One Modbus TCP frame as sent: its MBAP header's fields and its PDU."""

    tid: int
    protocol: int
    length: int
    unit: int
    pdu: bytes

    def encode(self) -> bytes:
        return struct.pack(">HHHB", self.tid, self.protocol, self.length, self.unit) + self.pdu


@st.composite
def tcp_frames(draw: st.DrawFn) -> TcpFrame:
    pdu = draw(modbus_pdus())
    protocol = draw(mostly(0, st.integers(0, 0xFFFF)))
    length = draw(mostly(len(pdu) + 1, st.sampled_from([0, 1, len(pdu), len(pdu) + 2]) |
                         st.integers(0, 0xFFFF)))
    return TcpFrame(draw(WORDS), protocol, length, draw(UNITS), pdu)


@dataclass(frozen=True)
class Stream:
    """Bytes sent in ``chunks`` (the cuts a TCP stack or a serial line may make)."""

    data: bytes
    cuts: tuple[int, ...]

    def chunks(self) -> list[bytes]:
        edges = sorted({0, len(self.data), *(c % (len(self.data) + 1) for c in self.cuts)})
        return [self.data[a:b] for a, b in itertools.pairwise(edges) if b > a]


def _streams(parts: st.SearchStrategy[bytes]) -> st.SearchStrategy[Stream]:
    """``parts`` (three in four) and junk, joined, cut anywhere."""
    frames = [parts.map(bytes) for _ in range(3)]  # one strategy each: drawn three times as often
    items = st.lists(st.one_of(*frames, st.binary(min_size=1, max_size=12)), min_size=1,
                     max_size=6)
    return st.builds(lambda ps, cuts: Stream(b"".join(ps), tuple(cuts)), items,
                     st.lists(st.integers(0, 2000), max_size=4))


def tcp_streams() -> st.SearchStrategy[Stream]:
    """Modbus TCP frames (and junk between them) as one stream, cut anywhere."""
    return _streams(tcp_frames().map(TcpFrame.encode))


@st.composite
def rtu_frames(draw: st.DrawFn, pdus: st.SearchStrategy[bytes] | None = None) -> bytes:
    """An RTU frame: unit, PDU, CRC (mostly right)."""
    frame = bytes([draw(UNITS)]) + draw(pdus or modbus_pdus())
    crc = crc16(frame)
    if draw(st.integers(0, 5)) == 0:
        crc = bytes([crc[0] ^ draw(st.integers(1, 255)), crc[1]])
    return frame + crc


def rtu_streams() -> st.SearchStrategy[Stream]:
    """RTU frames and noise on a serial line, cut anywhere."""
    return _streams(rtu_frames())


def flip(data: bytes, positions: list[int], masks: list[int]) -> bytes:
    """``data`` with the bits of ``masks`` flipped at ``positions`` (taken modulo its size)."""
    out = bytearray(data)
    for position, mask in zip(positions, masks, strict=False):
        if out:
            out[position % len(out)] ^= mask or 1
    return bytes(out)


@st.composite
def damaged(draw: st.DrawFn, data: bytes) -> bytes:
    """``data`` as a noisy line or a buggy peer may deliver it: bits flipped, cut short,
    grown, or replaced by anything."""
    how = draw(st.sampled_from(["flip", "cut", "grow", "replace", "flip"]))
    if how == "flip":
        n = draw(st.integers(1, 3))
        return flip(data, draw(st.lists(st.integers(0, 1 << 16), min_size=n, max_size=n)),
                    draw(st.lists(st.integers(1, 255), min_size=n, max_size=n)))
    if how == "cut":
        return data[:draw(st.integers(0, max(0, len(data) - 1)))]
    if how == "grow":
        return data + draw(st.binary(min_size=1, max_size=16))
    return draw(st.binary(max_size=max(8, len(data) + 4)))


# -- CAN ---------------------------------------------------------------------------------
#: the objects of hil's drive (index, sub-index, size in bytes): SDO requests name them mostly
def _drive_objects() -> list[tuple[int, int, int]]:
    from hil.emulators.drive.od import build_object_dictionary, iter_variables

    return [(v.index, v.subindex, max(1, len(v) // 8))
            for v in iter_variables(build_object_dictionary(1))]


DRIVE_OBJECTS = _drive_objects()
SDO_COMMANDS = st.one_of(
    st.sampled_from([0x40, 0x60, 0x70, 0x23, 0x27, 0x2B, 0x2F, 0x21, 0x20, 0x00, 0x10, 0x01,
                     0x11, 0x0B, 0x80, 0xA0, 0xA4, 0xC0, 0xC6, 0xE0]),
    st.integers(0, 255))


#: the objects whose writing means more than a value stored (the node's write effects), by
#: index: each as likely as the next, whatever its number of sub-indices
EFFECT_OBJECTS = st.sampled_from([0x1005, 0x1006, 0x1016, 0x1017, 0x1019, 0x1400, 0x1600,
                                  0x1800, 0x1A00, 0x2003, 0x2005, 0x6040, 0x605A, 0x6060]
                                 ).flatmap(lambda index: st.sampled_from(
                                     [o for o in DRIVE_OBJECTS if o[0] == index]))


#: a value written by SDO: small, a boundary, any, large, or a period [us] the node takes
#: (a multiple of its plant's 500 us, the longest among them)
SDO_VALUES = st.one_of(
    st.integers(0, 16), st.sampled_from([0x80, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF]),
    st.integers(0, 2**32 - 1), st.integers(2**24, 2**32 - 1),
    st.one_of(st.sampled_from([1, 2, 20, 2000, 2**32 // 500 - 1]),
              st.integers(1, 2**32 // 500 - 1)).map(lambda n: 500 * n))


def sdo_write(index: int, sub: int, size: int, value: int) -> bytes:
    """An expedited SDO download of ``value`` (``size`` bytes) to ``index:sub``."""
    return struct.pack("<BHBI", 0x23 | (4 - min(size, 4)) << 2, index, sub,
                       value & (1 << 8 * min(size, 4)) - 1)


@st.composite
def setting_writes(draw: st.DrawFn) -> bytes:
    """A write to an object whose writing means more than a stored value."""
    return sdo_write(*draw(EFFECT_OBJECTS), draw(SDO_VALUES))


@st.composite
def sdo_requests(draw: st.DrawFn) -> bytes:
    """An SDO request's 8 bytes (sometimes another length): mostly a write sized as its
    object (one with a write effect, or any), a read, another command for an object of the
    drive, or anything."""
    kind = draw(st.sampled_from(["write", "write", "read", "command", "any"]))
    objects = st.sampled_from(DRIVE_OBJECTS)
    if kind == "write":
        objects = st.one_of(EFFECT_OBJECTS, objects)
    elif kind == "any":
        objects = st.tuples(st.integers(0, 0xFFFF), st.integers(0, 255), st.integers(1, 4))
    index, sub, size = draw(objects)
    if kind == "write":
        command = 0x23 | (4 - min(size, 4)) << 2  # expedited, the object's size
    elif kind == "read":
        command = 0x40
    else:
        command = draw(SDO_COMMANDS)
    value = draw(SDO_VALUES)
    data = struct.pack("<BHBI", command, index, sub, value)
    if draw(st.integers(0, 7)) == 0:
        data = data[:draw(st.integers(0, 7))] if draw(st.booleans()) else data + b"\0"
    return data


def node_frames(node_id: int) -> st.SearchStrategy[tuple[int, bytes]]:
    """A frame a master or another node might put on the bus of drive ``node_id``."""
    mine = st.sampled_from([node_id, 0])
    return st.one_of(
        st.tuples(st.just(0x000), st.builds(bytes, st.tuples(
            st.sampled_from([1, 2, 0x80, 0x81, 0x82]) | st.integers(0, 255), mine))),
        st.tuples(st.just(0x000), st.binary(max_size=8)),
        st.tuples(st.just(0x080), st.sampled_from([b"", b"\x01", b"\xf0"]) |
                  st.binary(max_size=8)),
        *(st.tuples(st.just(0x600 + node_id), sdo_requests()) for _ in range(4)),  # richest
        st.tuples(st.just(0x200 + node_id), st.binary(max_size=8)),
        st.tuples(st.sampled_from([0x300, 0x400, 0x500]).map(lambda b: b + node_id),
                  st.binary(max_size=8)),
        st.tuples(st.just(0x77F), st.sampled_from([b"\x05", b"\x00", b""]) |
                  st.binary(max_size=8)),
        st.tuples(st.integers(0, 0x7FF), st.binary(max_size=8)),
    )


def bring_up(node_id: int, mode: int = 10) -> list[tuple[int, bytes]]:
    """The frames that take drive ``node_id`` to OPERATION ENABLED in ``mode`` (8 CSP, 10 CST),
    NMT started: the state the deeper paths (RPDOs, quick stop) need."""
    sdo = 0x600 + node_id
    return [(sdo, struct.pack("<BHBI", 0x2F, 0x6060, 0, mode)),
            (0x000, bytes([1, node_id])),
            *[(sdo, struct.pack("<BHBI", 0x2B, 0x6040, 0, word)) for word in (6, 7, 15)]]


def setting_frames(node_id: int) -> st.SearchStrategy[tuple[int, bytes]]:
    """A drive's settings written by SDO (mostly), with the SYNCs, RPDOs and NMT commands
    that make them take effect."""
    return st.one_of(
        *(st.tuples(st.just(0x600 + node_id), setting_writes()) for _ in range(3)),
        st.tuples(st.just(0x080), st.sampled_from([b"", b"\x01"])),
        st.tuples(st.just(0x200 + node_id), st.binary(max_size=8)),
        st.tuples(st.just(0x000), st.sampled_from([bytes([c, node_id]) for c in (1, 0x80)])),
    )
