"""``hil export``: one topic of a session to CSV (a spreadsheet, pandas) or JSON lines."""

from __future__ import annotations

import argparse
import csv
import io
import math
import sys
from typing import Any

from hil.cli.argtypes import output_file

#: below this many nanoseconds t / 1e9 rounded to 9 decimals is t / 1e9: doubles below 2^22
#: are at most 2^-30 apart, so t / 1e9 is within 2^-31 s (< 0.5e-9 s) of the 9-decimal number
#: and rounds back to it
_EXACT_NS = (1 << 22) * 10**9
CSV_BLOCK_ROWS = 8192  # rows formatted at a time: the text of a block, not of the topic
MEMO_VALUES = 65536  # distinct values a column keeps the text of (a few MB)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "export", help="write one topic of a session as CSV or JSON lines",
        description="Write the messages of one topic: one row per message, t_s (seconds from "
        "the session's start) and log_time_ns first, then one column per field (a list field "
        "becomes FIELD.0, FIELD.1, ...; a nested object FIELD.KEY). Works on split series and "
        "damaged files (what could be read). pandas: pd.read_csv(F).",
    )
    p.add_argument("file", help="session file (.mcap; the first file of a split series)")
    p.add_argument("--topic", required=True, metavar="TOPIC", help="the topic, e.g. "
                   "/bench/power, /drive/feedback, /events")
    form = p.add_mutually_exclusive_group()
    form.add_argument("--csv", action="store_true", help="CSV (the default)")
    form.add_argument("--jsonl", action="store_true", help="JSON lines, as 'hil report --topic'")
    p.add_argument("--out", metavar="F", type=output_file,
                   help="write here (default: standard output)")
    p.set_defaults(handler=export_command)


def export_command(args: argparse.Namespace) -> int:
    from hil.cli.report import topic_lines
    from hil.core.recording.reader import read_session

    data = read_session(args.file)
    if args.jsonl:
        text = "".join(line + "\n" for line in topic_lines(data, args.topic))
    else:
        text = csv_text(data, args.topic)
    if args.out:
        with open(args.out, "w", encoding="utf-8", newline="") as file:
            file.write(text)
        print(f"{args.topic}: {data.messages.count(args.topic)} row(s) to {args.out}",
              file=sys.stderr)  # a row per message (a text with a newline is one field)
    else:
        sys.stdout.write(text)
    return 0


def csv_text(data: Any, topic: str) -> str:
    """The topic as CSV text (header, then a row per message)."""
    import json

    from hil.cli.report import topic_lines

    out = io.StringIO()
    if _write_columns(data, topic, out):
        return out.getvalue()
    rows = [_flatten(json.loads(line)) for line in topic_lines(data, topic)]
    columns: list[str] = []
    for row in rows:
        columns.extend(key for key in row if key not in columns)
    writer = csv.DictWriter(out, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def _write_columns(data: Any, topic: str, out: io.StringIO) -> bool:
    """A CDR topic of single values (no lists) written column by column, the rows the same
    as :func:`~hil.cli.report.topic_lines` gives them, flattened (a message's own ``t_s``
    wins over the session time); False for any other topic."""
    from hil.cli.report import start_ns

    layout = data.messages.layout(topic) if topic in data.messages else None
    if layout is None or layout.count == 0 or any(f.sequence for f in layout.fields):
        return False
    log_times = data.messages.log_times(topic)
    columns = {"t_s": session_seconds(log_times, start_ns(data)),
               "log_time_ns": log_times.tolist()}
    for name in layout.names:
        values = layout.values(name)
        if values and isinstance(values[0], float) and not all(map(math.isfinite, values)):
            values = [v if math.isfinite(v) else None for v in values]  # as JSON's null
        columns[name] = values
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(columns)
    table = list(columns.values())
    if any(isinstance(column[0], str) for column in table):
        writer.writerows(zip(*table, strict=True))  # quoted as csv quotes them
        return True
    # numbers and booleans, cell by cell as csv.writer writes them (str; None as nothing),
    # column by column in blocks of rows: about a quarter less time than row by row
    makers = [_ColumnCells.for_column(column[:CSV_BLOCK_ROWS]) for column in table]
    for begin in range(0, len(log_times), CSV_BLOCK_ROWS):
        cells = [make(column[begin:begin + CSV_BLOCK_ROWS])
                 for make, column in zip(makers, table, strict=True)]
        out.write("\n".join(map(",".join, zip(*cells, strict=True))))
        out.write("\n")
    return True


def _cells(values: list[Any]) -> list[str]:
    """Numbers or booleans as csv.writer writes them: ``str``, None as nothing."""
    if None in values:
        return ["" if value is None else str(value) for value in values]
    return list(map(str, values))


class _ColumnCells:
    """:func:`_cells` of one column, block after block, each distinct value formatted once
    where the values repeat: a session holds many (a statusword, a position standing still, a
    current at its limit, a round trip's few microsecond steps, a sine's values period after
    period), and a dictionary lookup costs a tenth of a float's ``str``. A column whose first
    block never repeats (a time, a count) is formatted value by value; the memo is cleared
    past :data:`MEMO_VALUES` (the text of a long session stays a block's). Equal values of a
    column are one text (one type a column), but for the two zeros of floats: a block that
    holds both is formatted value by value."""

    def __init__(self) -> None:
        self.memo: dict[Any, str] | None = None  # None: value by value

    def __call__(self, values: list[Any]) -> list[str]:
        memo = self.memo
        if memo is None:
            return _cells(values)
        distinct = dict.fromkeys(values)
        if len(memo) + len(distinct) > MEMO_VALUES:
            memo.clear()
        for value in distinct:
            if value not in memo:
                memo[value] = "" if value is None else str(value)
        if values.count(0.0) and \
                len({str(value) for value in values if value == 0.0} | {memo[0.0]}) > 1:
            return _cells(values)  # 0.0 and -0.0
        return list(map(memo.__getitem__, values))

    @classmethod
    def for_column(cls, first_block: list[Any]) -> _ColumnCells:
        """Memoised unless every value of ``first_block`` is distinct (a time: the memo would
        cost a third more than it saves)."""
        cells = cls()
        if len(dict.fromkeys(first_block)) < len(first_block):
            cells.memo = {}
        return cells


def session_seconds(log_times: Any, start_ns: int) -> list[float]:
    """``round((t - start_ns) / 1e9, 9)`` of each log time [ns] (uint64), as ``hil report
    --topic`` gives ``t_s``; less than 2^22 s after the start that rounding changes nothing
    (the quotient is the double nearest the 9-decimal number already), and numpy divides as
    Python does."""
    import numpy as np

    if log_times.size and int(log_times.min()) >= start_ns and \
            int(log_times.max()) - start_ns < _EXACT_NS:
        return list(((log_times - np.uint64(start_ns)).astype(np.int64) / 1e9).tolist())
    return [round((t - start_ns) / 1e9, 9) for t in log_times.tolist()]


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        flat: dict[str, Any] = {}
        for key, item in value.items():
            flat.update(_flatten(item, f"{prefix}{key}."))
        return flat
    if isinstance(value, list):
        flat = {}
        for index, item in enumerate(value):
            flat.update(_flatten(item, f"{prefix}{index}."))
        return flat
    return {prefix[:-1]: value}
