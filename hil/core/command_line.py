"""The command line this process's sessions record: set by ``hil.cli.main`` before a command
runs, apart from :mod:`hil.core.session` so that a command that records nothing does not
import the loop and the recorder to set it."""

from __future__ import annotations

import sys
from collections.abc import Sequence

_command_line: list[str] | None = None


def set_command_line(argv: Sequence[str]) -> None:
    """The command line sessions of this process record (``hil.cli.main`` sets it, so a call
    of ``main([...])`` from Python records its own arguments, not the interpreter's)."""
    global _command_line
    _command_line = list(argv)


def command_line() -> list[str]:
    """The command line set last, else the interpreter's."""
    return _command_line if _command_line is not None else sys.argv
