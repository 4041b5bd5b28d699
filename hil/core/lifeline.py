"""Helper processes die with the process that started them, however it ends (SIGKILL too).

The parent starts a helper with :func:`lifeline_env` in its environment; the helper calls
:func:`die_with_parent` first thing. On Linux the kernel then sends the helper SIGTERM the
moment its parent dies (``prctl(PR_SET_PDEATHSIG)``); elsewhere a daemon thread watches the
parent's pid twice a second. A parent already gone when the helper starts ends it at once.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

from hil.core.libc import die_with_parent_signal

PARENT_ENV = "HIL_PARENT_PID"


def lifeline_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """``env`` (default: this process's) with this process named as the helper's parent."""
    return {**(os.environ if env is None else env), PARENT_ENV: str(os.getpid())}


def die_with_parent() -> None:
    """In a helper started with :func:`lifeline_env`: end when the parent ends (no-op when
    not started so)."""
    text = os.environ.pop(PARENT_ENV, "")
    if not text.isdigit():
        return
    parent = int(text)
    die_with_parent_signal(signal.SIGTERM)
    if os.getppid() != parent:  # gone before the lifeline was tied
        os.kill(os.getpid(), signal.SIGTERM)
        return
    if not sys.platform.startswith("linux"):
        threading.Thread(target=_watch, args=(parent,), daemon=True).start()


def _watch(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(0.5)
    os.kill(os.getpid(), signal.SIGTERM)
