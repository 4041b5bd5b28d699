"""``hil export`` writes a CDR topic of single values column by column: the CSV must be, byte
for byte, the one the message-by-message rows give (``hil report --topic``'s JSON lines,
flattened), whatever the values: NaN and infinities (empty, as JSON's null), a message's own
``t_s`` (it wins over the session time), strings a CSV must quote, float32 values."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from hil.cli import export as export_module
from hil.cli.export import _EXACT_NS, _flatten, csv_text, session_seconds
from hil.cli.report import topic_lines
from hil.core.recording.cdr import CdrEncoder, Field, ros2msg_text
from hil.core.recording.mcap_writer import McapWriter
from hil.core.recording.reader import read_session
from tests.cli import hil_here

FIELDS = [Field("t_s", "float64"), Field("position_deg", "float64"),
          Field("current_mA", "float32"), Field("word", "uint16"), Field("fresh", "bool"),
          Field("path", "string"), Field("count", "int64")]
VALUES = [0.0, 1.5, float("nan"), float("inf"), -float("inf"), 1e300, -0.0, 1 / 3]
TEXTS = ["", "qp", "a,b", 'say "x"', "two\nlines", "naïve", " lead"]


def write_session(path: Path, messages: list[dict], fields: list[Field]) -> None:
    encode = CdrEncoder(fields).encode
    with open(path, "wb") as stream:
        writer = McapWriter(stream)
        writer.start()
        schema = writer.register_schema("t", "ros2msg", ros2msg_text(fields).encode())
        channel = writer.register_channel("/t", "cdr", schema)
        events = writer.register_channel("/events", "json",
                                         writer.register_schema("e", "jsonschema", b"{}"))
        writer.add_message(events, 1_000, b'{"kind": "start"}', 1_000)  # the session's start
        for k, message in enumerate(messages):
            writer.add_message(channel, 5_000 + 500_000 * k, encode(message), 0)
        writer.finish()


def rows_as_before(data, topic: str) -> str:
    """The CSV of ``topic`` from its JSON lines, row by row (the way for every topic)."""
    rows = [_flatten(json.loads(line)) for line in topic_lines(data, topic)]
    columns: list[str] = []
    for row in rows:
        columns.extend(key for key in row if key not in columns)
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def test_a_cdr_topic_exports_as_its_rows_do(tmp_path, capsys):
    messages = [{"t_s": VALUES[k % 8], "position_deg": VALUES[(k + 3) % 8],
                 "current_mA": [*VALUES[:5], 3.4e38, *VALUES[6:]][(k + 5) % 8],
                 "word": k * 997 % 65536, "fresh": k % 3 == 0, "path": TEXTS[k % 7],
                 "count": -k * 10**12} for k in range(60)]
    path = tmp_path / "s.mcap"
    write_session(path, messages, FIELDS)
    data = read_session(path)
    assert data.messages.layout("/t") is not None  # the columns' way, not the rows'
    text = csv_text(data, "/t")
    assert text == rows_as_before(data, "/t")
    table = list(csv.DictReader(io.StringIO(text)))
    assert [r["path"] for r in table[:7]] == TEXTS and table[2]["t_s"] == ""  # NaN
    assert table[1]["log_time_ns"] == "505000" and table[1]["t_s"] == "1.5"  # its own t_s
    done = hil_here(capsys, "export", str(path), "--topic", "/t", "--out", "t.csv",
                    cwd=tmp_path)
    assert done.returncode == 0 and "60 row(s) to t.csv" in done.stderr
    assert (tmp_path / "t.csv").read_text(encoding="utf-8") == text


def test_a_topic_of_numbers_exports_as_its_rows_do_block_by_block(tmp_path, monkeypatch):
    """No strings: the cells are made column by column, a block of rows at a time (blocks of 7
    here: rows across blocks, a last one short), NaN and infinities left empty."""
    monkeypatch.setattr(export_module, "CSV_BLOCK_ROWS", 7)
    fields = [field for field in FIELDS if field.type != "string"]
    messages = [{"t_s": VALUES[k % 8], "position_deg": VALUES[(k + 3) % 8],
                 "current_mA": [*VALUES[:5], 3.4e38, *VALUES[6:]][(k + 5) % 8],
                 "word": k * 997 % 65536, "fresh": k % 3 == 0, "count": -k * 10**12}
                for k in range(60)]
    path = tmp_path / "s.mcap"
    write_session(path, messages, fields)
    data = read_session(path)
    text = csv_text(data, "/t")
    assert text == rows_as_before(data, "/t")
    table = list(csv.DictReader(io.StringIO(text)))
    assert len(table) == 60 and table[2]["t_s"] == "" and table[6]["current_mA"] == ""  # inf
    assert table[2]["current_mA"] == "0.3333333432674408"  # float32's 1/3
    assert table[59]["count"] == str(-59 * 10**12) and table[57]["fresh"] == "True"


def test_repeated_values_are_formatted_once_and_exported_as_their_rows(tmp_path, monkeypatch):
    """Columns whose values repeat (a memo of each distinct value's text, cleared when full):
    the same CSV, the two zeros told apart in a block that holds both and in blocks that hold
    one each, non-finite values empty, a time that never repeats value by value."""
    monkeypatch.setattr(export_module, "CSV_BLOCK_ROWS", 6)
    monkeypatch.setattr(export_module, "MEMO_VALUES", 4)
    fields = [Field("position_deg", "float64"), Field("current_mA", "float32"),
              Field("word", "uint16"), Field("fresh", "bool"), Field("count", "int64")]
    zeros = [0.0, 0.0, 1.5, 0.0, 2.5, 1.5,        # a block with +0.0 alone
             -0.0, 1.5, -0.0, 2.5, 1.5, 2.5,      # -0.0 alone, the memo holding +0.0's text
             0.0, -0.0, float("nan"), 1.5, 0.0, -0.0,  # both zeros in one block
             3.5, 4.5, 5.5, 6.5, 7.5, float("inf")]    # more than the memo holds
    messages = [{"position_deg": zeros[k], "current_mA": [0.0, 1 / 3, -0.0][k % 3],
                 "word": k % 2, "fresh": k % 4 == 0, "count": k // 3} for k in range(24)]
    path = tmp_path / "s.mcap"
    write_session(path, messages, fields)
    data = read_session(path)
    text = csv_text(data, "/t")
    assert text == rows_as_before(data, "/t")
    positions = [row["position_deg"] for row in csv.DictReader(io.StringIO(text))]
    assert positions[:9] == ["0.0", "0.0", "1.5", "0.0", "2.5", "1.5", "-0.0", "1.5", "-0.0"]
    assert positions[12:15] == ["0.0", "-0.0", ""] and positions[-1] == ""


def test_a_topic_without_its_own_t_s_counts_from_the_sessions_start(tmp_path):
    fields = [Field("position_deg", "float64"), Field("word", "uint8")]
    path = tmp_path / "s.mcap"
    write_session(path, [{"position_deg": k / 7, "word": k} for k in range(5)], fields)
    data = read_session(path)
    text = csv_text(data, "/t")
    assert text == rows_as_before(data, "/t")
    assert text.splitlines()[:3] == ["t_s,log_time_ns,position_deg,word", "4e-06,5000,0.0,0",
                                     "0.000504,505000,0.14285714285714285,1"]


def test_a_topic_of_lists_exports_row_by_row(tmp_path):
    fields = [Field("t_s", "float64"), Field("u_mA", "float32", sequence=True)]
    path = tmp_path / "s.mcap"
    write_session(path, [{"t_s": k, "u_mA": [1.5] * (k % 3)} for k in range(5)], fields)
    data = read_session(path)
    text = csv_text(data, "/t")
    assert text == rows_as_before(data, "/t")
    assert text.splitlines()[0] == "t_s,log_time_ns,u_mA.0,u_mA.1"


@given(start=st.integers(0, 1 << 62), since=st.lists(
    st.integers(0, _EXACT_NS - 1) | st.integers(0, 1 << 62) | st.sampled_from(
        [0, 1, 500_000, _EXACT_NS - 1, _EXACT_NS]), max_size=20))
def test_session_seconds_are_the_rounded_quotients_of_the_rows(start, since):
    times = np.array([start + s for s in since], dtype=np.uint64)
    want = [round((t - start) / 1e9, 9) for t in times.tolist()]
    assert session_seconds(times, start) == want
