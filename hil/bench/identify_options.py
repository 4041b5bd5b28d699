"""What ``hil bench identify`` can set, light enough for the command line's parsing (the
experiment itself is :mod:`hil.bench.identify`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from hil.errors import UsageError

MACHINING_MODES = ("sequence", "prbs", "off")


@dataclass
class IdentifyOptions:
    """Everything ``hil bench identify`` can set (CLI flags); None = the config's value."""

    relays: tuple[str, ...] = ("P1", "P2")
    duration_s: float = 300.0
    min_hold_s: float | None = None
    seed: int = 1
    bench: str = "emulated"
    machining: str = "off"
    meter_quantity: str = "va_l2"
    realtime: bool = False
    out: str | None = None
    config_path: str | None = None
    progress_s: float = 10.0
    lab: Mapping[str, Any] | None = None  # the labgrid place of --place (hil.lab.place)


def parse_relays(text: str) -> tuple[str, ...]:
    """``P1,P2`` -> ("P1", "P2"); ``none`` or empty -> ()."""
    if text.strip().lower() in ("", "none"):
        return ()
    names = tuple(n.strip() for n in text.split(","))
    if any(not n for n in names) or len(set(names)) != len(names):
        raise UsageError(f"--relays {text!r}: expected distinct relay names separated by ','"
                         ", e.g. P1,P2")
    return names
