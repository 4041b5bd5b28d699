"""Warnings for the person at the terminal: one line on stderr each (``hil: warning: ...``,
``hil: unsafe: ...``), whatever else records them (a session's ``/events``)."""

from __future__ import annotations

import sys


def warn(message: str) -> None:
    """``hil: warning: <message>`` on stderr, at once."""
    print(f"hil: warning: {message}", file=sys.stderr, flush=True)


def unsafe(message: str) -> None:
    """``hil: unsafe: <message>`` on stderr, at once: outputs that may not be at their safe
    level after a run."""
    print(f"hil: unsafe: {message}", file=sys.stderr, flush=True)
