"""The configuration reference (docs/CONFIGURATION.md), generated from what runs: every key
as the readers read the packaged configs (its kind, the rule it is held to, its default), the
comments of the packaged files that describe it, and the flags of ``hil servo run`` and
``hil bench run`` with the key each one sets. ``python -m hil.cli.config_reference`` prints it;
``make docs`` writes it; a test holds the committed file to it, so it cannot drift.
"""

from __future__ import annotations

import argparse
import json
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from importlib import resources
from typing import Any

from hil.core.config import unit_of
from hil.core.settings import Setting

#: the origin of a key read from an example (a table the packaged file has not)
EXAMPLE = "example"
#: what the packaged drive.toml says of [[axis]] in its comments
AXIS_TABLE = ("Several axes, one drive each, the axes of a bus cycled on its one SYNC (as `hil "
              "servo run --axes x=1,y=2`): one table per axis, its name (topics "
              "/axis/NAME/..., KPIs), its drive's node id, if it needs one of its own, its "
              "current limit (the smaller of it and master.current_limit_mA holds) and, on a "
              "bus of its own, that bus's URL (bus; \"\": the run's, --drive or [bus]). No "
              "default: without [[axis]] a run drives one axis.")
_TABLE = re.compile(r"^\s*\[\[?([A-Za-z0-9_.\"-]+)\]\]?\s*(#.*)?$")
_KEY = re.compile(r"^\s*([A-Za-z0-9_\"]+)\s*=")
# a key the packaged file leaves out (its default: none), shown commented out with an example
_LEFT_OUT = re.compile(r"^#\s*([A-Za-z0-9_]+)\s*=\s*[^#]*#\s*(.*)$")

INTRO = """\
# Configuration reference

Generated from the code that reads the configuration (`python -m hil.cli.config_reference`, `make
docs`): the kinds, rules and defaults below are the ones the readers check, and the
descriptions are the comments of the packaged files (`hil/configs/*.toml`). Do not edit by hand.

## How a value is chosen

Every setting of a run comes from one order, the later winning key by key:

1. the built-in default (a key the packaged file leaves out);
2. the packaged config (`hil/configs/drive.toml` for the drive, `hil/configs/bench.toml` and
   `hil/configs/eec.toml` for the bench);
3. your `--config F.toml`, laid over it table by table (name only what differs);
4. the flags of the command line (and the keyword options of `hil.api`).

`hil servo run --print-config` and `hil bench run --print-config` print every setting as the
run would use it and where it came from, and exit (`--json` for JSON: `{"KEY": {"value",
"origin"}}`); a run records the same under the `settings` key of the session's `config`
metadata. The printed text is a config file that `--config` takes back as it is; the run's
options, which are flags, are printed as comments with the command line that runs it again.

A path in a config file (`master.eds`, `models.*`) is relative to the folder of the file that
names it; a path given as a flag, to the working folder.

Safety and current limits only tighten from a flag: `--umax` above `master.current_limit_mA`
needs `--allow-higher-current`, a `--safety` (or, for the bench, `--dwell`) value looser than the
configured one needs `--allow-looser-safety`; the run then prints a warning and records it in
the session. A config file may set any value its rule allows.

An unknown key, a value of the wrong kind (a string where a number belongs) or a value outside
its rule is one error line naming the file (or the flag) and the key, with its unit. The keys
are checked with the flags' rules, when the file is read: a misspelt key names the closest one
(`current_limit_ma`: "did you mean 'master.current_limit_mA'?"), a value written with its unit
is refused with the number to write (`following_error_ms = "2s"`: "'2s' is 2000"), and a
current below 1 mA as most likely amperes (`current_limit_mA = 0.3`, as `--umax 0.3`).
"""


def toml_comments(text: str) -> dict[str, str]:
    """The comments of a TOML file by dotted key: a key's comment on its line and the comment
    lines that continue it; a table's (under ``[TABLE]``), the comment lines right under its
    header; a key the file leaves out, from its commented-out example line (``# name = 4096
    # what it is``) and the lines that continue it."""
    comments: dict[str, str] = {}
    table, current = "", None
    for line in text.splitlines():
        stripped = line.strip()
        header = _TABLE.match(line)
        if header:
            table = header.group(1).replace('"', "")
            current = f"[{table}]"
            continue
        left_out = _LEFT_OUT.match(line)
        if left_out:
            current = f"{table}.{left_out.group(1)}" if table else left_out.group(1)
            comments[current] = left_out.group(2).strip()
            continue
        if stripped.startswith("#"):  # a table's own lines, or a key's indented follow-ups
            words = stripped.lstrip("#").strip()
            follows = current is not None and (current.startswith("[") or line[0] == " ")
            if current is not None and follows and words:
                comments[current] = f"{comments.get(current, '')} {words}".strip()
            elif not follows:
                current = None
            continue
        key = _KEY.match(line)
        if key is None:
            current = None if not stripped else current
            continue
        name = key.group(1).replace('"', "")
        current = f"{table}.{name}" if table else name
        comment = _comment_of(line)
        comments[current] = comment
    return comments


def _comment_of(line: str) -> str:
    """The comment at the end of a ``key = value`` line (``#`` inside a string is not one)."""
    in_string = None
    for i, char in enumerate(line):
        if char in "\"'" and in_string in (None, char):
            in_string = None if in_string == char else char
        elif char == "#" and in_string is None:
            return line[i + 1:].strip()
    return ""


def _describe(key: str, comments: Mapping[str, str]) -> str:
    """A key's description: its own comment, else that of the key whose inline table holds
    it (``relays.P1`` for ``relays.P1.coil``)."""
    head = key
    while head:
        if comments.get(head):
            text = comments[head]
            return text if head == key else f"(of `{head}`) {text}"
        head = head.rpartition(".")[0]
    return ""


def _value(setting: Setting) -> str:
    unit = unit_of(setting.key)
    rule = f" {setting.rule}" if setting.rule else ""
    return f"{setting.kind}{rule}" + (f" [{unit}]" if unit else "")


def _default(setting: Setting) -> str:
    if setting.value is None:
        return "(none)"
    value = setting.value
    if setting.kind == "path" and isinstance(value, str):  # as the packaged file writes it
        value = value.removeprefix(str(resources.files("hil.configs")) + os.sep)
    text = json.dumps(value)
    text = f"`{text}`" if len(text) <= 40 else f"`{text[:37]}...`"
    return f"e.g. {text}" if setting.origin == EXAMPLE else text


def _cell(text: str) -> str:
    """``text`` as one Markdown table cell: its bars escaped, and ``][`` too (``[-END][:K=V]``
    would read as a reference link)."""
    return text.replace("|", "\\|").replace("\n", " ").replace("][", "]\\[")


def key_tables(settings: Sequence[Setting], comments: Mapping[str, str],
               flags: Mapping[str, str]) -> list[str]:
    """The keys as Markdown tables, one per TOML table; ``flags``: key -> the flag that sets
    it."""
    lines: list[str] = []
    table, told = None, set()
    for setting in settings:
        head, _, name = setting.key.rpartition(".")
        if head != table:
            table = head
            lines += ["", f"### `[{head}]`" if head else "### top level", ""]
            parts = head.split(".")
            for outer in (".".join(parts[:n]) for n in range(1, len(parts) + 1)):
                if comments.get(f"[{outer}]") and outer not in told:
                    told.add(outer)
                    lines += [_cell(comments[f"[{outer}]"]), ""]
            lines += ["| key | kind, rule [unit] | default | flag | what it is |",
                      "|---|---|---|---|---|"]
        flag = _flag_for(setting.key, flags)
        lines.append(f"| `{name}` | {_cell(_value(setting))} | {_cell(_default(setting))} | "
                     f"{f'`{flag}`' if flag else ''} | "
                     f"{_cell(_describe(setting.key, comments))} |")
    return lines


def _flag_for(key: str, flags: Mapping[str, str]) -> str:
    for pattern, flag in flags.items():
        if re.fullmatch(pattern.replace(".", r"\.").replace("*", "[^.]+"), key):
            return flag
    return ""


def flag_table(parser: argparse.ArgumentParser, flags: Mapping[str, str]) -> list[str]:
    """The flags of a run command, with their help and the key each sets."""
    keys_of: dict[str, list[str]] = {}
    for key, flag in flags.items():
        keys_of.setdefault(flag.split()[0], []).append(key)
    lines = ["| flag | sets | what it does |", "|---|---|---|"]
    for action in parser._actions:
        names = [name for name in action.option_strings if name.startswith("--")]
        if not names or names[0] == "--help":
            continue
        flag = names[0]
        sets = ", ".join(f"`{k}`" for k in keys_of.get(flag, [])) or "(the run)"
        lines.append(f"| `{flag}` | {sets} | {_cell(action.help or '')} |")
    return lines


def _run_parser(command: str) -> argparse.ArgumentParser:
    from hil.cli.main import build_parser

    parser: Any = build_parser()
    for name in (command, "run"):
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[name]
    return parser  # type: ignore[no-any-return]


def _section(title: str, files: Iterable[str], settings: Sequence[Setting],
             flags: Mapping[str, str], command: str) -> list[str]:
    comments: dict[str, str] = {}
    for name in files:
        comments.update(toml_comments(
            resources.files("hil.configs").joinpath(name).read_text("utf-8")))
    keys = [s for s in settings if not s.key.startswith("run.")]
    comments["[[axis]]"] = AXIS_TABLE
    return [f"## {title}", "", f"### The flags of `hil {command} run`", "",
            *flag_table(_run_parser(command), flags), *key_tables(keys, comments, flags), ""]


def reference() -> str:
    """docs/CONFIGURATION.md."""
    from hil.bench.run import BenchRunOptions
    from hil.bench.settings import FLAG_KEYS as BENCH_FLAGS
    from hil.bench.settings import resolve_bench
    from hil.servo.run import ServoRunOptions
    from hil.servo.settings import FLAG_KEYS as SERVO_FLAGS
    from hil.servo.settings import resolve_servo

    # [[axis]] is not in the packaged file (one would make every run a run on several axes):
    # its keys are read from an example
    axes = [{"name": "x", "node": 1, "current_limit_mA": 800.0}, {"name": "y", "node": 2}]
    servo = [s for s in resolve_servo(ServoRunOptions(
        controller="", drive_overrides={"axis": axes})).settings()
        if s.key != "axis" and not s.key.startswith("axis[1]")]
    servo = [Setting(s.key.replace("axis[0]", "[axis]"), s.value, EXAMPLE, s.kind, s.rule)
             if s.key.startswith("axis[0]") else s for s in servo]
    bench = resolve_bench(BenchRunOptions(controller="")).settings()
    return "\n".join([
        INTRO,
        *_section("The servo drive: `hil servo run`, drive.toml", ["drive.toml"], servo,
                  SERVO_FLAGS, "servo"),
        *_section("The relay bench: `hil bench run`, bench.toml and eec.toml",
                  ["bench.toml", "eec.toml"], bench, BENCH_FLAGS, "bench"),
    ]).rstrip() + "\n"


if __name__ == "__main__":
    print(reference(), end="")
