"""MCAP bytes into hil's session reader: a session written by hil's own MCAP writer (JSON and
CDR topics in several zstd chunks, metadata, an attachment), then damaged: bits flipped,
spans overwritten, bytes inserted, a copy cut short; mostly near the start of a record,
where a record's opcode and length are. Read from a real file, as ``hil report`` reads it.

The rule for the reader: it reads what it can or raises a
:class:`~hil.errors.SessionFileError` of one line; every topic it finds decodes (to a message
or to an ``_undecodable`` marker); and a file whose messages came out different from what
was written is never called intact (``recovered`` false). Metadata and attachments are left
out of that comparison: the writer leaves the data section's CRC at 0, so a changed metadata
value cannot be seen.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass

from hypothesis import strategies as st

from hil.core.recording.cdr import CdrEncoder, fields_of, ros2msg_text
from hil.core.recording.mcap_walk import Walk, walk
from hil.core.recording.mcap_writer import McapWriter
from hil.core.recording.reader import SessionData, read_session
from hil.errors import SessionFileError
from tests.fuzz.harness import Check, Target, bound, clear_error

FEEDBACK = {"type": "object", "title": "Feedback", "properties": {
    "position_deg": {"type": "number"}, "current_mA": {"type": "number", "x-cdr": "float32"},
    "fresh": {"type": "boolean"}, "state": {"type": "string"},
    "tpdo": {"type": "array", "items": {"type": "integer", "x-cdr": "uint16"}}}}
EVENT = {"type": "object", "title": "Event"}


def session_bytes() -> bytes:
    """A small session as hil writes one: two topics in ~6 chunks, metadata, an attachment."""
    stream = io.BytesIO()
    writer = McapWriter(stream, chunk_size=600)
    writer.start("hil")
    fields = fields_of(FEEDBACK)
    encode = CdrEncoder(fields).encode
    cdr = writer.register_channel("/drive/feedback", "cdr", writer.register_schema(
        "hil/msg/Feedback", "ros2msg", ros2msg_text(fields).encode()))
    events = writer.register_channel("/events", "json", writer.register_schema(
        "Event", "jsonschema", json.dumps(EVENT).encode()))
    writer.add_metadata("config", {"drive": "[master]\nnode_id = 1\n"})
    for k in range(60):
        t_ns = k * 500_000
        writer.add_message(cdr, t_ns, encode({"position_deg": k / 7, "current_mA": -k,
                                              "fresh": k % 5 > 0, "state": "OE",
                                              "tpdo": [k, 2 * k]}), t_ns)
        if k % 10 == 0:
            writer.add_message(events, t_ns, json.dumps({"kind": "tick", "k": k}).encode(),
                               t_ns)
    writer.add_attachment(0, 0, "drive.toml", "application/toml", b"[master]\n")
    writer.finish()
    return stream.getvalue()


ORIGINAL = session_bytes()


def record_starts(data: bytes) -> list[int]:
    """Where each top-level record of ``data`` starts (the magic's end first)."""
    starts, pos = [8], 8
    while pos + 9 <= len(data):
        pos += 9 + int.from_bytes(data[pos + 1:pos + 9], "little")
        starts.append(pos)
    return starts


STARTS = record_starts(ORIGINAL)


@dataclass(frozen=True)
class Harm:
    """One change to the file: ``kind`` at ``offset``, with ``data``."""

    kind: str     # flip, overwrite, insert, cut
    offset: int
    data: bytes

    def apply(self, data: bytes) -> bytes:
        at = self.offset % (len(data) + 1)
        if self.kind == "cut":
            return data[:at]
        if self.kind == "insert":
            return data[:at] + self.data + data[at:]
        if self.kind == "overwrite":
            return data[:at] + self.data + data[at + len(self.data):]
        out = bytearray(data)
        for i, mask in enumerate(self.data):
            if at + i < len(out):
                out[at + i] ^= mask or 1
        return bytes(out)


OFFSETS = st.one_of(st.builds(lambda start, k: start + k, st.sampled_from(STARTS),
                              st.integers(0, 24)),
                    st.integers(0, len(ORIGINAL)))
HARMS = st.builds(Harm, st.sampled_from(["flip", "flip", "overwrite", "insert", "cut"]),
                  OFFSETS, st.binary(min_size=1, max_size=12))


def messages(data: bytes) -> dict[str, list[tuple[int, object]]]:
    session = read_session_bytes(data)
    return {topic: list(session.messages[topic]) for topic in session.messages}


def read_session_bytes(data: bytes, path: str | None = None) -> SessionData:
    if path is None:
        with tempfile.TemporaryDirectory() as folder:
            return read_session_bytes(data, os.path.join(folder, "s.mcap"))
    with open(path, "wb") as file:
        file.write(data)
    return read_session(path)


@contextlib.contextmanager
def rig() -> Iterator[Check]:
    state = Walk()
    list(walk(ORIGINAL, state))
    assert state.finished and not state.damage  # what the cases damage is a whole session
    written = messages(ORIGINAL)
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "session.mcap")

        def check(harms: list[Harm]) -> None:
            data = ORIGINAL
            for harm in harms:
                data = harm.apply(data)
            with bound("reading a damaged session"):
                try:
                    session = read_session_bytes(data, path)
                except SessionFileError as exc:
                    clear_error(exc)
                    return
                found = {topic: list(session.messages[topic]) for topic in session.messages}
                for topic in found:
                    session.arrays(topic)
                session.duration_s()
                assert isinstance(session.lost_messages, int | None)
            if not session.recovered:
                assert found == written, "messages differ from those written, yet the " \
                                         "session is called intact"

        yield check


TARGETS = (
    Target("mcap-reader", st.lists(HARMS, min_size=1, max_size=3), rig, examples=150,
           # found: the first chunk's opcode 0x06 -> 0x07 lost its messages, read as intact
           regressions=([Harm("flip", STARTS[2], b"\x01")],)),
)
