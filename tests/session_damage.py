"""Damage a session file on purpose and hold what the reader gives back against the bound.

Every chunk of a session spans at most ``CHUNK_SPAN_S`` of session time (the recorder closes
it then, in lockstep as in real time), so a damage loses at most that much session time per
chunk it touches, less what the reader salvages of a damaged chunk up to its damage. What
:func:`damage_report` measures of one damaged copy: the messages recovered, those lost (each
counted once, by topic, log time and content), the chunks the damage touched, the session
time each lost, and whether every recovered message is one of the original's.

``python tests/session_damage.py F.mcap [--offsets N]`` prints the salvage figures of a file:
for N cuts and N 4 KiB overwrites spread over it, the messages recovered against the bound.
"""

from __future__ import annotations

import argparse
import io
import marshal
import struct
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import MessageIndex

from hil.core.recording.chunk_check import ChunkCheck
from hil.core.recording.reader import SessionData, read_session

CHUNK_SPAN_S = 1.0  # the recorder's default: a chunk closes once it spans this much
OVERWRITE_BYTES = 4096
#: topic, log time, the decoded message marshalled: its content, types, key order and -0.0 told
#: apart as its repr tells them apart, at a sixth of repr's CPU; format 2, which writes every
#: object out (no references: two equal strings read by two paths give the same bytes)
Item = tuple[str, int, bytes]


@dataclass(frozen=True)
class ChunkPlace:
    """Where a chunk lies in the file (its check record included) and what it holds."""

    start: int
    end: int
    start_ns: int
    end_ns: int
    keys: frozenset[tuple[str, int]]  # (topic, log time) of its messages


@dataclass(frozen=True)
class DamageReport:
    recovered: int             # messages read from the damaged copy
    lost: int                  # of the original's, not read back
    foreign: int               # read back, but not one of the original's (must be 0)
    touched: int               # chunks the damage touched (started before a cut)
    lost_span_s: list[float]   # per touched chunk, the session time its lost messages span
    outside: int               # lost messages of chunks the damage did not touch (must be 0)
    said_lost: int | None      # the reader's lost_messages
    said_recovered: bool       # the reader's recovered flag
    salvaged: int              # messages the reader says it read from damaged chunks


def items_of(data: SessionData) -> Counter[Item]:
    return Counter((topic, t, marshal.dumps(message, 2)) for topic in data.messages
                   for t, message in data.topic(topic))


def chunk_places(path: Path) -> list[ChunkPlace]:
    """The chunks of an intact file, from its summary and message indexes."""
    blob = path.read_bytes()
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    topics = {channel.id: channel.topic for channel in summary.channels.values()}
    places = []
    for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        start = index.chunk_start_offset
        record = blob[start:start + index.chunk_length]
        check = ChunkCheck.of(record, 0, 0, 0).record()  # its length: the one before the chunk
        keys = set()
        for offset in index.message_index_offsets.values():
            (length,) = struct.unpack_from("<Q", blob, offset + 1)
            entries = MessageIndex.read(ReadDataStream(io.BytesIO(
                blob[offset + 9:offset + 9 + length])))
            keys.update((topics[entries.channel_id], t) for t, _ in entries.records)
        places.append(ChunkPlace(start - len(check), start + index.chunk_length,
                                 index.message_start_time, index.message_end_time,
                                 frozenset(keys)))
    return places


def damage_report(original: Counter[Item], places: list[ChunkPlace], damaged: Path,
                  first: int, last: int | None) -> DamageReport:
    """What the reader gives back of ``damaged``, a copy of the original whose bytes
    ``first`` to ``last`` are damaged, or (``last`` None) which is cut at ``first``: the
    messages of the chunks after a cut are lost by the cut, not counted."""
    data = read_session(damaged)
    got = items_of(data)
    if last is None:
        touched = [p for p in places if p.start < first < p.end]
        cut_off = {key for p in places if p.start >= first for key in p.keys}
    else:
        touched = [p for p in places if p.start < last and p.end > first]
        cut_off = set()
    place_of = {key: n for n, p in enumerate(touched) for key in p.keys}
    lost_times: dict[int, list[int]] = {}
    lost = outside = 0
    for (topic, t, _), count in (original - got).items():
        if (topic, t) in cut_off:
            continue
        lost += count
        if (topic, t) in place_of:
            lost_times.setdefault(place_of[(topic, t)], []).append(t)
        else:
            outside += count
    return DamageReport(
        recovered=sum(got.values()), lost=lost, foreign=sum((got - original).values()),
        touched=len(touched),
        lost_span_s=[(max(ts) - min(ts)) / 1e9 for ts in lost_times.values()],
        outside=outside, said_lost=data.lost_messages, said_recovered=data.recovered,
        salvaged=sum(d.salvaged or 0 for d in data.damage))


def offsets(size: int, count: int) -> list[int]:
    """``count`` offsets spread over a file of ``size`` bytes, past its magic."""
    return [8 + (size - 8 - OVERWRITE_BYTES) * k // max(1, count - 1) for k in range(count)]


def salvage_table(path: Path, count: int) -> str:
    """The salvage figures of ``path`` (an intact session), one line per damaged copy."""
    blob = path.read_bytes()
    original = items_of(read_session(path))
    places = chunk_places(path)
    total = sum(original.values())
    lines = [f"{path.name}: {total} messages, {len(places)} chunks, bound "
             f"{CHUNK_SPAN_S:g} s of session time per chunk touched",
             f"{'damage':<22}{'recovered':>10}{'lost':>7}{'salvaged':>9}{'chunks':>8}"
             f"{'lost s':>8}{'said lost':>10}"]
    copy = path.with_name(f"{path.stem}.damaged.mcap")
    for offset in offsets(len(blob), count):
        for kind in ("cut", "overwrite"):
            last = None if kind == "cut" else offset + OVERWRITE_BYTES
            copy.write_bytes(blob[:offset] if last is None else
                             blob[:offset] + bytes(OVERWRITE_BYTES) + blob[last:])
            r = damage_report(original, places, copy, offset, last)
            lines.append(f"{kind + ' at ' + str(offset):<22}{r.recovered:>10}{r.lost:>7}"
                         f"{r.salvaged:>9}{r.touched:>8}{max(r.lost_span_s, default=0):>8.3f}"
                         f"{r.said_lost!s:>10}")
    copy.unlink()
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("session", type=Path)
    parser.add_argument("--offsets", type=int, default=12)
    args = parser.parse_args()
    print(salvage_table(args.session, args.offsets))
    sys.exit(0)
