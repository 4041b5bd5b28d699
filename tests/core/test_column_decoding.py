"""A CDR topic decoded column by column (:mod:`hil.core.recording.cdr_columns`, what the reader
does) gives exactly what the per-message decoder gives: every field of every message, its value
and its Python type, and every ``SessionData.arrays`` column, its dtype, shape and values. For
every schema hil records as CDR and for any flat schema (hypothesis draws the fields, their
order and the messages), wherever the messages lie among other bytes; and a topic with a
message its schema does not describe (cut short, a length past its end, bytes that are not
UTF-8) reads as it did message by message, that message undecodable and the others whole."""

from __future__ import annotations

import functools
import math
import string
import struct
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hil.controllers.base import POSITION, VELOCITY
from hil.core.loop import TIMING_SCHEMA
from hil.core.recording.cdr import (
    PRIMITIVES,
    CdrDecoder,
    CdrEncoder,
    CdrError,
    Field,
    fields_of,
    ros2msg_text,
)
from hil.core.recording.cdr_columns import CdrColumns, as_array
from hil.core.recording.mcap_writer import McapWriter
from hil.core.recording.reader import SessionData, read_session
from hil.servo.axes import CONTOUR_SCHEMA
from hil.servo.motion import MOTION_SCHEMA
from hil.servo.topics import (
    COMMAND_SCHEMA,
    FEEDBACK_SCHEMA,
    PREDICTION_SCHEMA,
    STOP_SCHEMA,
    command_schema,
)

#: the servo's, a move's, a path's and the loop's topics, as hil records them; the bench's are
#: all float32 (power, levels) or all uint8 (relays): BENCH_LIKE below, and the drawn schemas
HIL_SCHEMAS = {
    "/drive/command": COMMAND_SCHEMA,
    "/drive/command (position)": command_schema(POSITION),
    "/drive/command (velocity)": command_schema(VELOCITY),
    "/drive/feedback": FEEDBACK_SCHEMA,
    "/drive/stop": STOP_SCHEMA,
    "/mpc/prediction": PREDICTION_SCHEMA,
    "/drive/motion": MOTION_SCHEMA,
    "/path/contour": CONTOUR_SCHEMA,
    "/loop/TASK/timing": TIMING_SCHEMA,
}
BENCH_LIKE = {
    "/bench/power": [Field(name, "float32") for name in ("va_l1", "va_l2", "va_l3", "total_va")],
    "/bench/relays": [Field(name, "uint8") for name in ("M1", "M2", "M1_commanded", "link_up")],
}
SCHEMAS = {**{topic: fields_of(schema) for topic, schema in HIL_SCHEMAS.items()}, **BENCH_LIKE}
_INT_RANGES = {kind: (-(1 << (8 * size - 1)), (1 << (8 * size - 1)) - 1) if code.islower() else
               (0, (1 << (8 * size)) - 1)
               for kind, (code, size) in PRIMITIVES.items() if code not in "fd?"}


def values_of(f: Field) -> st.SearchStrategy[Any]:
    """A field's values as a message may hold them (None: left out, written as zero)."""
    if f.type == "string":
        item: st.SearchStrategy[Any] = st.text(st.characters(codec="utf-8"), max_size=12)
    elif f.type == "bool":
        item = st.booleans()
    elif f.type == "float32":
        item = st.floats(width=32)
    elif f.type == "float64":
        item = st.floats()
    else:
        low, high = _INT_RANGES[f.type]
        item = st.integers(low, high) | st.sampled_from([low, high, 0])
    return st.none() | (st.lists(item, max_size=4) if f.sequence else item)


def messages_of(fields: list[Field], size: int = 12) -> st.SearchStrategy[list[dict]]:
    return _messages_of(tuple(fields), size)


@functools.cache
def _messages_of(fields: tuple[Field, ...], size: int) -> st.SearchStrategy[list[dict]]:
    """One strategy per schema, not one per example: hypothesis checks a new strategy's
    structure before its first draw (a third of test_a_topic_with_a_damaged_message...)."""
    return st.lists(st.fixed_dictionaries({f.name: values_of(f) for f in fields}),
                    min_size=1, max_size=size)


@st.composite
def flat_fields(draw: st.DrawFn) -> list[Field]:
    """Any flat schema: up to 9 fields of any primitive or string, sequences among them."""
    kinds = draw(st.lists(st.tuples(st.sampled_from([*PRIMITIVES, "string"]), st.booleans()),
                          max_size=9))
    return [Field(f"{string.ascii_lowercase[k]}_{kind}", kind, sequence)
            for k, (kind, sequence) in enumerate(kinds)]


@st.composite
def laid_among_other_bytes(draw: st.DrawFn, payloads: list[bytes]
                           ) -> tuple[bytes, np.ndarray, np.ndarray]:
    """The payloads in one buffer, other bytes before, between and after them, as a session's
    buffer holds a topic's messages among its other records: the buffer, starts and sizes."""
    buffer, starts = bytearray(), []
    for payload in payloads:
        buffer += draw(st.binary(max_size=9))
        starts.append(len(buffer))
        buffer += payload
    buffer += draw(st.binary(max_size=9))
    return bytes(buffer), np.array(starts, dtype=np.int64), \
        np.array([len(p) for p in payloads], dtype=np.int64)


def same(a: Any, b: Any) -> bool:
    """Equal values of the same types, NaN equal to NaN and -0.0 apart from 0.0."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return (math.isnan(a) and math.isnan(b)) or (a == b and math.copysign(1, a) ==
                                                     math.copysign(1, b))
    if isinstance(a, dict):
        return list(a) == list(b) and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and same(a.tolist(), b.tolist())
    return bool(a == b)


def hold_against_per_message(fields: list[Field], payloads: list[bytes],
                             placed: tuple[bytes, np.ndarray, np.ndarray]) -> None:
    """The layout's messages and columns against CdrDecoder's, message by message."""
    layout = CdrColumns(fields).lay_out(np.frombuffer(placed[0], np.uint8), *placed[1:])
    assert layout is not None
    decoder = CdrDecoder(fields)
    want = [decoder.decode(p) for p in payloads]
    have = layout.messages()
    for k, (w, h) in enumerate(zip(want, have, strict=True)):
        assert same(w, h), f"message {k}: {h} != {w}"
    for f in fields:
        assert same(layout.column(f.name), as_array([m[f.name] for m in want])), f.name


@pytest.mark.parametrize("topic", sorted(SCHEMAS))
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_every_topic_hil_records_decodes_column_by_column_as_message_by_message(topic, data):
    fields = SCHEMAS[topic]
    encode = CdrEncoder(fields).encode
    payloads = [encode(m) for m in data.draw(messages_of(fields))]
    hold_against_per_message(fields, payloads, data.draw(laid_among_other_bytes(payloads)))


@pytest.mark.slow  # a second or more: make test runs it, make check does not
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_any_flat_schema_decodes_column_by_column_as_message_by_message(data):
    fields = data.draw(flat_fields())
    if any(f.sequence and f.type == "string" for f in fields):
        fields = [f for f in fields if not (f.sequence and f.type == "string")]
    encode = CdrEncoder(fields).encode
    payloads = [encode(m) for m in data.draw(messages_of(fields, size=20))]
    # trailing bytes after the last field: the per-message decoder reads past them, so do we
    padded = [p + data.draw(st.binary(max_size=3)) for p in payloads]
    hold_against_per_message(fields, padded, data.draw(laid_among_other_bytes(padded)))


def topic_of(fields: list[Field], payloads: list[bytes], times: list[int]) -> SessionData:
    """A session file of one CDR topic ``/t`` holding ``payloads``, written and read back."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "t.mcap"
        with open(path, "wb") as stream:
            writer = McapWriter(stream)
            writer.start()
            schema = writer.register_schema("t", "ros2msg", ros2msg_text(fields).encode())
            channel = writer.register_channel("/t", "cdr", schema)
            for t, payload in zip(times, payloads, strict=True):
                writer.add_message(channel, t, payload, t)
            writer.finish()
        return read_session(path)


def per_message(fields: list[Field], payload: bytes) -> Any:
    """What the per-message decoder makes of a payload: its dict, or the mark of one it
    cannot read."""
    try:
        return CdrDecoder(fields).decode(payload)
    except (CdrError, ValueError, IndexError, struct.error):
        return {"_undecodable": len(payload)}


def reference_arrays(messages: list[Any]) -> dict[str, np.ndarray]:
    """``SessionData.arrays`` from decoded messages: every key any message has, in order."""
    keys: list[str] = []
    for message in messages:
        keys.extend(k for k in message if k not in keys)
    return {key: as_array([m.get(key) for m in messages]) for key in keys}


def damaged(payload: bytes, how: str, at: int) -> bytes:
    """``payload`` cut, or with a byte changed (a length, a string's byte, the header)."""
    if how == "cut":
        return payload[:at % (len(payload) + 1)]
    at %= len(payload)
    return payload[:at] + bytes([payload[at] ^ 0xFF]) + payload[at + 1:]


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), topic=st.sampled_from(sorted(SCHEMAS)), how=st.sampled_from(["cut",
                                                                                   "flip"]))
@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_a_topic_with_a_damaged_message_reads_as_message_by_message(data, topic, how):
    fields = SCHEMAS[topic]
    encode = CdrEncoder(fields).encode
    payloads = [encode(m) for m in data.draw(messages_of(fields))]
    k = data.draw(st.integers(0, len(payloads) - 1))
    payloads[k] = damaged(payloads[k], how, data.draw(st.integers(0, 1 << 16)))
    session = topic_of(fields, payloads, list(range(len(payloads))))
    want = [per_message(fields, p) for p in payloads]
    assert same([m for _, m in session.topic("/t")], want)
    arrays = session.arrays("/t")
    assert same(dict(arrays), {"log_time_ns": np.arange(len(payloads), dtype=np.int64),
                               **reference_arrays(want)})


def test_a_string_that_is_not_utf8_makes_its_message_undecodable_and_only_it():
    fields = fields_of(COMMAND_SCHEMA)
    encode = CdrEncoder(fields).encode
    payloads = [encode({"t_s": k * 0.5, "path": "qp"}) for k in range(3)]
    payloads[1] = payloads[1].replace(b"qp\x00", b"q\xff\x00")
    session = topic_of(fields, payloads, [0, 1, 2])
    messages = [m for _, m in session.topic("/t")]
    assert messages[1] == {"_undecodable": len(payloads[1])}
    assert [messages[0]["path"], messages[2]["t_s"]] == ["qp", 1.0]
    assert session.arrays("/t")["t_s"].dtype == object  # None where undecodable, as before


def test_columns_are_decoded_only_when_read():
    fields = fields_of(COMMAND_SCHEMA)
    encode = CdrEncoder(fields).encode
    session = topic_of(fields, [encode({"t_s": k * 0.5, "command_mA": k}) for k in range(4)],
                       [0, 1, 2, 3])
    arrays = session.arrays("/t")
    assert list(arrays) == ["log_time_ns", *(f.name for f in fields)]
    assert "command_mA" in arrays and "command_mA" not in arrays._arrays  # not decoded yet
    assert arrays["command_mA"].tolist() == [0.0, 1.0, 2.0, 3.0]
    assert list(arrays._arrays) == ["log_time_ns", "command_mA"]
    with pytest.raises(KeyError):
        arrays["nope"]


def test_a_topic_with_a_sequence_of_strings_reads_message_by_message():
    fields = [Field("t_s", "float64"), Field("names", "string", sequence=True),
              Field("n", "int32")]
    encode = CdrEncoder(fields).encode
    sent = [{"t_s": 0.5 * k, "names": ["a", "bc"][:k % 3], "n": -k} for k in range(5)]
    session = topic_of(fields, [encode(m) for m in sent], [0, 1, 2, 3, 4])
    assert [m for _, m in session.topic("/t")] == sent
    assert session.arrays("/t")["n"].tolist() == [0, -1, -2, -3, -4]


def test_messages_read_in_log_time_order_those_logged_together_in_file_order():
    fields = fields_of(MOTION_SCHEMA)
    encode = CdrEncoder(fields).encode
    session = topic_of(fields, [encode({"controlword": k}) for k in range(6)],
                       [30, 10, 20, 10, 0, 30])
    assert [(t, m["controlword"]) for t, m in session.topic("/t")] == \
        [(0, 4), (10, 1), (10, 3), (20, 2), (30, 0), (30, 5)]
    arrays = session.arrays("/t")
    assert arrays["log_time_ns"].tolist() == [0, 10, 10, 20, 30, 30]
    assert arrays["controlword"].tolist() == [4, 1, 3, 2, 0, 5]
    assert session.messages.span_ns("/t") == (0, 30) and session.messages.count("/t") == 6
