"""``hil`` run by ``main`` in the test's own process: the cheap way to check a variant of a
command that another test already runs from outside, in a subprocess (a process start costs
about a second of CPU; the suite starts hundreds)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path
from typing import Any

import pytest

from hil.cli.main import main

#: what a pytest process of a user's tests leaves out: the plugins of hil's own test tools and
#: lab extra (hypothesis's, labgrid's), which cost some 0.65 s of CPU to start and are not what
#: these tests try; hil's plugin loads as installed (tests/integration/test_busy_machine.py
#: runs a user's pytest with every plugin)
NOT_A_USERS_PLUGINS = ("-p", "no:hypothesispytest", "-p", "no:labgrid")


def hil_in(folder: str | os.PathLike[str], *args: Any) -> int:
    """``hil ARGS`` run in this process from ``folder``: its exit status (an argument the parser
    refused included). What it prints goes to the test's output: for a module's fixture, which
    has no ``capsys``; a test checks what a command prints with :func:`hil_here`."""
    argv = [str(arg) for arg in args]
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(Path(folder))
        try:
            return main(argv)
        except SystemExit as exit_:  # the parser refused an argument
            return int(exit_.code or 0)


def hil_here(capture: Any, *args: Any, cwd: str | os.PathLike[str] | None = None
             ) -> subprocess.CompletedProcess[str]:
    """``hil ARGS`` run in this process (from ``cwd``, else the current folder), reported as
    :func:`subprocess.run` reports a process: its exit status (an argument the parser refused
    included) and what it printed to ``capture`` (pytest's ``capsys``, or ``capfd``, which also
    holds what the session writer process printed)."""
    capture.readouterr()
    status = hil_in(Path.cwd() if cwd is None else cwd, *args)
    out, err = capture.readouterr()
    return subprocess.CompletedProcess(["hil", *map(str, args)], status, out, err)
