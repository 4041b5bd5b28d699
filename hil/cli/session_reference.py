"""The session format reference (docs/reference/sessions.md), generated from sessions that
run: a servo run (MPC, one axis), a servo run on two axes (a circle), a profile move and a
bench run (EEC), each a short lockstep run on the emulators, recorded as every run is and read
back with hil's reader. Each topic is shown with its encoding and its schema as the file holds
it (a JSON Schema, or the ros2msg text of a CDR topic); each metadata record with what
:data:`METADATA` says it holds, and a record no entry describes fails the generation.
``python -m hil.cli.session_reference`` prints it; ``make docs`` writes it; a test holds the
committed page to it.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

#: what each metadata record of a session holds (name, or name prefix ending in "/")
METADATA = {
    "session": "the kind of run (`servo`, `bench`, `motion`...), its clock (`sim`: lockstep, "
               "`realtime`), the base period [s], the wall time it started and the command "
               "line (`argv`, JSON)",
    "versions": "the version of Python, hil and every package a run depends on",
    "config": "`json`: every setting of the run as it ran, with `settings` (each key's value "
              "and origin: default, packaged config, `--config`, flag)",
    "loop": "the loop's tasks, their periods and timing summary",
    "kpis": "`json`: the run's KPIs, the `--json` document (`status`, `stop_reason`, limits)",
    "reference": "where the reference was placed: its start, offset and how (one axis)",
    "reference/": "the same per axis (`reference/NAME`)",
    "drive": "`json`: the drive as the master found and configured it: identity, scaling "
             "and where each value came from, the current limit chain, the objects put back",
    "bus_plan": "`json`: the bus time plan of a run on several axes, per bus",
    "bench": "where the bench was, what it said it is (Modbus device identification) and whose "
             "time it kept",
    "motion": "`json`: the profile or homing settings a move or homing held",
    "realtime": "each hardening step of a real-time loop, granted or refused",
    "realtime.": "the same for an emulator process a real-time run started "
                 "(`realtime.emulator`)",
    "live": "what the live view served: `sent`, decimated, `client_queue_full`",
    "resim": "a resimulation's `of` (the recording), `controller`, `params` and `plant`",
    "recorder": "how the recording ended: messages dropped per topic, a session that ended "
                "without closing",
}

#: the sample runs, each (file name, run): lockstep on the emulators, short
Runs = dict[str, Callable[[str], Any]]


def sample_runs() -> Runs:
    from hil import api

    return {
        "servo.mcap": lambda out: api.run_servo("mpc", duration_s=0.01, out=out),
        "axes.mcap": lambda out: api.run_servo(
            "pid", duration_s=0.01, out=out, axes="x=1,y=2",
            reference="circle:radius=2,feed=20"),
        "move.mcap": lambda out: api.move_drive(1.0, "emulated", out=out),
        "bench.mcap": lambda out: api.run_bench("eec", duration_s=1.0, out=out),
    }


def describe_metadata(name: str) -> str:
    if name in METADATA:
        return METADATA[name]
    for prefix, text in METADATA.items():
        if prefix[-1] in "/." and name.startswith(prefix):
            return text
    raise KeyError(f"metadata record {name!r} is not described in "
                   "hil.cli.session_reference.METADATA: say what it holds there")


def _cell(text: str) -> str:
    """``text`` as one Markdown table cell: its bars escaped, and ``][`` too (``[-END][:K=V]``
    would read as a reference link)."""
    return text.replace("|", "\\|").replace("\n", " ").replace("][", "]\\[")


def json_schema_lines(schema: Mapping[str, Any]) -> list[str]:
    lines = []
    if schema.get("description"):
        lines += [" ".join(str(schema["description"]).split()), ""]
    properties = schema.get("properties", {})
    if properties:
        lines += ["| field | type | what it is |", "|---|---|---|"]
        for name, spec in properties.items():
            kind = spec.get("type", "")
            if kind == "array":
                kind = f"array of {spec.get('items', {}).get('type', '')}"
            lines.append(f"| `{name}` | {_cell(str(kind))} | "
                         f"{_cell(' '.join(str(spec.get('description', '')).split()))} |")
        lines.append("")
    return lines


def topic_lines(topic: str, encoding: str, schema: Mapping[str, Any],
                sessions: list[str]) -> list[str]:
    title = schema.get("title", "")
    lines = [f"### `{topic}`", "",
             f"{encoding.upper()}" + (f", `{title}`" if title else "")
             + f"; in {', '.join(sessions)}", ""]
    if "ros2msg" in schema:
        lines += ["```text", str(schema["ros2msg"]).strip(), "```", ""]
    else:
        lines += json_schema_lines(schema)
    return lines


def generalised(topic: str) -> str:
    """A per-axis or per-task topic under its pattern (``/axis/x/feedback`` ->
    ``/axis/NAME/feedback``)."""
    parts = topic.split("/")
    if len(parts) > 3 and parts[1] == "axis":
        parts[2] = "NAME"
    if len(parts) > 3 and parts[1] == "loop":
        parts[2] = "TASK"
    return "/".join(parts)


INTRO = """\
# Session format

Generated from sessions that ran (`python -m hil.cli.session_reference`, `make docs`): a servo
run with the MPC on one axis, a servo run on two axes following a circle, a profile move and a
bench run with the EEC, each in lockstep on the emulators, read back with hil's reader. Do not
edit by hand. How sessions are written, split, read and recovered is in [Sessions and
reports](../guides/sessions.md) and [the architecture](../ARCHITECTURE.md#sessions-mcap).

A session is an MCAP file (or a series `OUT_000.mcap`, `OUT_001.mcap`... of complete files),
zstd-compressed, with:

- **topics**: low-rate ones as JSON with a JSON Schema (`jsonschema`), the high-rate ones as
  CDR with a `ros2msg` schema (field names lower case; the JSON name is in a comment, and
  hil's reader, `hil report` and `hil export` give back the JSON names). `--encoding json`
  records every topic as JSON, `--topic-encoding /TOPIC=json|cdr` one topic. A message's log
  time is the clock's time (virtual in lockstep, real in real time) in ns;
- **metadata** records (string maps; a `json` key holds a JSON document);
- **attachments**: the configuration file the run read.
"""


def reference(folder: str | os.PathLike[str] | None = None) -> str:
    """docs/reference/sessions.md, from sample runs recorded into ``folder`` (a temporary
    folder when None)."""
    from hil.core.recording.reader import read_session

    with tempfile.TemporaryDirectory() as scratch:
        where = Path(folder or scratch)
        topics: dict[str, tuple[str, dict[str, Any], list[str]]] = {}
        metadata: dict[str, list[str]] = {}
        attachments: dict[str, list[str]] = {}
        cwd = os.getcwd()
        os.chdir(where)  # the runs' own files (sessions/...) stay in the scratch folder
        try:
            for name, run in sample_runs().items():
                run(str(where / name))
                data = read_session(where / name)
                label = f"`{name.removesuffix('.mcap')}`"
                for topic in data.topic_counts:
                    pattern = generalised(topic)
                    entry = topics.setdefault(pattern, (data.encodings[topic],
                                                        data.schemas.get(topic, {}), []))
                    if label not in entry[2]:
                        entry[2].append(label)
                for record in data.metadata:
                    record = "reference/NAME" if record.startswith("reference/") else record
                    if label not in metadata.setdefault(record, []):
                        metadata[record].append(label)
                for attachment in data.attachments:
                    attachments.setdefault(attachment, []).append(label)
        finally:
            os.chdir(cwd)
    lines = [INTRO, "## Topics", ""]
    for topic in sorted(topics):
        encoding, schema, sessions = topics[topic]
        lines += topic_lines(topic, encoding, schema, sessions)
    lines += ["## Metadata", "", "| record | what it holds | in |", "|---|---|---|"]
    named = {**{n: [] for n in METADATA if n[-1] not in "/."}, **metadata}
    for record in sorted(named):
        where_found = ", ".join(metadata.get(record, [])) or "(runs of other kinds)"
        lines.append(f"| `{record}` | {_cell(describe_metadata(record))} | {where_found} |")
    lines += ["", "## Attachments", "", "| file | in |", "|---|---|"]
    lines += [f"| `{name}` | {', '.join(found)} |" for name, found in sorted(attachments.items())]
    return "\n".join(lines).rstrip() + "\n"


if __name__ == "__main__":
    print(reference(), end="")
