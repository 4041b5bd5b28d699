"""Positions relative to where each run started, for runs that started there.

A servo run started from where its axis stands (``--from-here``; the ``hil_drive`` fixture's
default) records its start in the session's ``reference`` metadata (``reference/NAME`` per
axis: ``placed`` "from here", ``start_deg``). Two such runs repeat one motion from wherever
their axis stood, so a comparison takes their positions (:data:`POSITION_FIELDS` of the
axis' topics) relative to each run's own start; a run placed on the nearest turn is compared
as recorded."""

from __future__ import annotations

from collections.abc import Mapping

from hil.core.recording.reader import SessionData

#: the fields that hold an axis position [deg] (``/drive/feedback``, ``/drive/command``...)
POSITION_FIELDS = ("position_deg", "reference_deg")
FROM_HERE = "from here"


def run_starts(data: SessionData) -> dict[str, float | None]:
    """Each axis' topic prefix (``/drive/``, ``/axis/NAME/``) and where it started [deg] when
    its reference was placed there, else None (placed on the nearest turn)."""
    starts: dict[str, float | None] = {}
    for name, record in data.metadata.items():
        if name != "reference" and not name.startswith("reference/"):
            continue
        prefix = "/drive/" if name == "reference" else f"/axis/{name.split('/', 1)[1]}/"
        try:
            start = float(record["start_deg"])
        except (KeyError, ValueError):
            continue
        starts[prefix] = start if record.get("placed") == FROM_HERE else None
    return starts


def axis_of(signal: str, starts: Mapping[str, float | None]) -> str | None:
    """The axis prefix of ``signal`` (``TOPIC:FIELD``) when it is a position of an axis a
    session placed, else None."""
    topic, _, field = signal.rpartition(":")
    if field not in POSITION_FIELDS:
        return None
    return next((prefix for prefix in starts if topic.startswith(prefix)), None)


def start_offsets(signals: list[str], base: SessionData, cand: SessionData,
                  notes: list[str]) -> list[tuple[float, float] | None]:
    """For each of ``signals``, (the baseline's start, the candidate's) to subtract when both
    runs started from where their axis stood, else None; ``notes`` says which were taken
    relative, and which could not be (one run placed otherwise)."""
    ours, theirs = run_starts(base), run_starts(cand)
    offsets: list[tuple[float, float] | None] = []
    told: set[str] = set()
    for signal in signals:
        prefix = axis_of(signal, ours)
        b, c = (ours.get(prefix), theirs.get(prefix)) if prefix else (None, None)
        offsets.append((b, c) if b is not None and c is not None else None)
        if prefix is None or prefix not in theirs or prefix in told:
            continue
        told.add(prefix)
        axis = prefix.strip("/")
        if b is not None and c is not None:
            notes.append(f"{axis} positions relative to each run's start: both started where "
                         f"the axis stood (--from-here), the baseline at {b:.6g} deg, the "
                         f"candidate at {c:.6g} deg")
        elif (b is None) != (c is None):
            here = "baseline" if b is not None else "candidate"
            notes.append(f"{axis} positions compared as recorded: the {here} started where "
                         "its axis stood (--from-here), the other on the turn nearest it")
    return offsets
