"""Warnings for the person at the terminal: one line on stderr each (``hil: warning: ...``),
whatever else records them (a session's ``/events``)."""

from __future__ import annotations

import sys


def warn(message: str) -> None:
    """``hil: warning: <message>`` on stderr, at once."""
    print(f"hil: warning: {message}", file=sys.stderr, flush=True)
