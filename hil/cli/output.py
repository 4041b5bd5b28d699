"""What the commands print as JSON: always valid JSON (RFC 8259 has no NaN nor Infinity)."""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from hil.core.settings import Setting


#: what ``--quiet`` leaves out, on every command that shows progress while it works
QUIET_HELP = "no progress line on the terminal (there is none when stderr is not a terminal)"


def add_quiet_argument(parser: argparse.ArgumentParser, help: str = QUIET_HELP) -> None:
    """``--quiet``: no progress while the command works (its result is printed all the
    same)."""
    parser.add_argument("--quiet", action="store_true", help=help)


def finite(value: Any) -> Any:
    """``value`` with every non-finite float (NaN, inf) replaced by None, recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(item) for item in value]
    return value


def json_text(value: Any) -> str:
    """``value`` as indented JSON, non-finite numbers as null, other objects as text."""
    return json.dumps(finite(value), indent=2, default=str, allow_nan=False)


def print_settings(title: str, settings: Sequence[Setting], as_json: bool) -> int:
    """``--print-config``: every setting as a run would use it and its origin (JSON:
    ``{key: {"value", "origin"}}``); the exit status, 0."""
    from hil.core.printed_config import format_settings
    from hil.core.settings import settings_json

    print(json_text(settings_json(settings)) if as_json else format_settings(title, settings),
          end="\n" if as_json else "")
    return 0
