"""This process's C library, for the few calls the ``os`` module lacks (``prctl``,
``mlockall``): the symbols the process already has (``dlopen(NULL)``), found once. Not
``ctypes.util.find_library``, which runs ``ldconfig`` (or a compiler) at every call."""

from __future__ import annotations

import ctypes
import functools
import signal
import sys

PR_SET_PDEATHSIG = 1


@functools.cache
def libc() -> ctypes.CDLL | None:
    """The C library (``ctypes.get_errno()`` reads its errno), or None where there is none."""
    try:
        return ctypes.CDLL(None, use_errno=True)
    except (OSError, TypeError):  # TypeError: Windows has no process-wide symbol table
        return None


def die_with_parent_signal(sig: int = signal.SIGTERM) -> bool:
    """Have the kernel send this process ``sig`` when the thread that started it ends (Linux's
    ``PR_SET_PDEATHSIG``); whether it was set."""
    library = libc()
    if library is None or not sys.platform.startswith("linux"):
        return False
    try:
        return bool(library.prctl(PR_SET_PDEATHSIG, sig, 0, 0, 0) == 0)
    except AttributeError:  # a C library without prctl
        return False
