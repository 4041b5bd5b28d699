"""What the HTML report draws: panels of traces over session time, from a session's kind or
from a named signal (``/topic:field``).

An application registers ``kind = "module:function"`` in the entry-point group
``hil.html_panels``; the function takes the session and its origin (the log time of its
first message, ns) and returns its :class:`Panel` s, as the ``hil.plotters`` do for the PNG.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hil.core.plugins import registered
from hil.core.recording.reader import SessionData
from hil.errors import UsageError

PANELS_GROUP = "hil.html_panels"


@dataclass(frozen=True)
class Trace:
    """One line: ``y`` over ``t_s`` (seconds from the session's first message). ``step``
    holds each value until the next sample (a relay); ``dash`` draws it dashed (a
    reference)."""

    name: str
    t_s: np.ndarray
    y: np.ndarray
    step: bool = False
    dash: bool = False


@dataclass(frozen=True)
class Panel:
    """One row of the report's plot: its traces over time, horizontal ``lines`` (a limit, a
    bound: value and label) and, where the y axis is categorical, its ``ticks``."""

    title: str
    y_label: str
    traces: tuple[Trace, ...]
    lines: tuple[tuple[float, str], ...] = ()
    ticks: tuple[tuple[float, str], ...] = ()


PanelMaker = Callable[[SessionData, int], list[Panel]]


def find_panels(kind: str) -> PanelMaker | None:
    """The panel maker registered for sessions of ``kind``, or None."""
    maker: PanelMaker | None = registered(PANELS_GROUP, kind)
    return maker


def origin_ns(data: SessionData) -> int:
    """The log time the report counts session time from: the session's first message."""
    span = data.time_range_ns()
    return span[0] if span else 0


def session_panels(data: SessionData, origin: int | None = None) -> list[Panel]:
    """The panels of the session's kind (none for a kind without a panel maker), on session
    time from ``origin`` [ns] (default: :func:`origin_ns`)."""
    maker = find_panels(data.metadata.get("session", {}).get("kind", ""))
    if maker is None:
        return []
    return maker(data, origin_ns(data) if origin is None else origin)


def signal_trace(data: SessionData, signal: str, name: str | None = None,
                 origin: int | None = None) -> Trace:
    """The trace of ``/topic:field`` in the session (time from ``origin`` [ns], default
    :func:`origin_ns`); a UsageError names what there is."""
    topic, sep, field = signal.rpartition(":")
    if not sep or not topic.startswith("/") or not field:
        raise UsageError(f"signal {signal!r}: expected /TOPIC:FIELD, e.g. "
                         "/drive/feedback:position_deg")
    if topic not in data.messages:
        raise UsageError(f"signal {signal!r}: no topic {topic!r} in {data.path}; topics: "
                         f"{', '.join(sorted(data.messages))}")
    arrays = data.arrays(topic)
    values = arrays.get(field)
    numeric = [key for key, a in arrays.items()
               if key != "log_time_ns" and a.ndim == 1 and a.dtype.kind in "biuf"]
    if values is None or field not in numeric:
        raise UsageError(f"signal {signal!r}: {topic} has no numeric field {field!r}; "
                         f"fields: {', '.join(numeric)}")
    t_s = (arrays["log_time_ns"] - (origin_ns(data) if origin is None else origin)) / 1e9
    return Trace(name or signal, t_s, np.asarray(values, float))
