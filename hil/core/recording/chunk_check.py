"""hil's chunk check: a private MCAP record before each chunk that says how much of a damaged
chunk is still the writer's bytes.

A chunk's own CRC covers its whole uncompressed content: one bad byte, and the stock readers
lose every message of it. The check record (opcode :data:`OPCODE`, in the range the MCAP
specification leaves to applications; readers skip it) holds the chunk record's length, its
message count and time range, and the CRC-32 of each :data:`PIECE_BYTES` piece of the chunk
record, plus a CRC of its own. The session reader (:mod:`hil.core.recording.mcap_walk`) takes
the pieces before the first bad one as intact and decompresses that prefix as far as it goes;
the zstd stream is cut into blocks of :data:`BLOCK_BYTES` (:func:`compress_in_blocks`), so what
is lost is the block where the damage starts and what follows it in the chunk.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import zstandard

OPCODE = 0xB1
TAG = b"hilcheck"
PIECE_BYTES = 4096
BLOCK_BYTES = 8 * 1024  # of uncompressed records: files 0.5-1 % larger than with zstd's 128 KiB
_FIELDS = struct.Struct("<8sQQQQII")  # tag, chunk length, messages, start, end, piece, count
_HEAD = struct.Struct("<BQ")
_CRC = struct.Struct("<I")


@dataclass(frozen=True)
class ChunkCheck:
    """What the writer knew of the chunk that follows."""

    chunk_length: int  # the chunk record's bytes, its opcode and length included
    message_count: int
    start_ns: int
    end_ns: int
    piece_bytes: int
    crcs: tuple[int, ...]

    @classmethod
    def of(cls, chunk_record: bytes, message_count: int, start_ns: int, end_ns: int,
           piece_bytes: int = PIECE_BYTES) -> ChunkCheck:
        """The check of a chunk record (all its bytes, opcode first)."""
        view = memoryview(chunk_record)
        crcs = tuple(zlib.crc32(view[at:at + piece_bytes])
                     for at in range(0, len(view), piece_bytes))
        return cls(len(chunk_record), message_count, start_ns, end_ns, piece_bytes, crcs)

    def record(self) -> bytes:
        """The check as an MCAP record: opcode, length, body (its own CRC last)."""
        body = _FIELDS.pack(TAG, self.chunk_length, self.message_count, self.start_ns,
                            self.end_ns, self.piece_bytes, len(self.crcs))
        body += struct.pack(f"<{len(self.crcs)}I", *self.crcs)
        body += _CRC.pack(zlib.crc32(body))
        return _HEAD.pack(OPCODE, len(body)) + body

    @classmethod
    def parse(cls, body: bytes) -> ChunkCheck | None:
        """The check of a record body; None when it is not one, or damaged."""
        if len(body) < _FIELDS.size + _CRC.size or not body.startswith(TAG):
            return None
        if zlib.crc32(body[:-_CRC.size]) != _CRC.unpack_from(body, len(body) - _CRC.size)[0]:
            return None
        _, length, count, start, end, piece, n = _FIELDS.unpack_from(body)
        if len(body) != _FIELDS.size + 4 * n + _CRC.size or piece <= 0 or length <= _HEAD.size:
            return None
        return cls(length, count, start, end, piece,
                   struct.unpack_from(f"<{n}I", body, _FIELDS.size))

    def intact_bytes(self, chunk_record: bytes | memoryview) -> int:
        """How many leading bytes of ``chunk_record`` (as found: a file cut short may end in
        it) are the writer's: the pieces before the first whose CRC differs, and the bytes of
        a piece the end of the file cut (a cut does not change the bytes before it)."""
        view = memoryview(chunk_record)[:self.chunk_length]
        for k, crc in enumerate(self.crcs):
            at = k * self.piece_bytes
            piece = view[at:at + self.piece_bytes]
            if len(piece) < min(self.piece_bytes, self.chunk_length - at):
                return len(view)
            if zlib.crc32(piece) != crc:
                return at
        return len(view)


def compress_in_blocks(records: bytes, compressor: zstandard.ZstdCompressor) -> bytes:
    """``records`` as one zstd frame (any reader decodes it at once) whose blocks each hold
    at most :data:`BLOCK_BYTES` of them: a streaming decoder given an intact prefix of the
    frame gives back every block in it."""
    stream = compressor.compressobj(size=len(records))
    view = memoryview(records)
    out = bytearray()
    for at in range(0, len(view), BLOCK_BYTES):
        out += stream.compress(view[at:at + BLOCK_BYTES])
        out += stream.flush(zstandard.COMPRESSOBJ_FLUSH_BLOCK)
    out += stream.flush()
    return bytes(out)
