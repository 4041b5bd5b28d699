"""Calling a user's code from the loop: one-line descriptions of what went wrong, a time
budget, and :class:`~hil.errors.ControllerError` instead of a traceback."""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hil.errors import ControllerError, HilError


def describe_exception(exc: BaseException) -> str:
    """``ValueError: bad gain (my_ctl.py:12 in decide)``: the type, the message and the
    innermost frame, on one line."""
    frames = traceback.extract_tb(exc.__traceback__)
    where = ""
    if frames:
        frame = frames[-1]
        where = f" ({Path(frame.filename).name}:{frame.lineno} in {frame.name})"
    message = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {message}{where}" if message else \
        f"{type(exc).__name__}{where}"


def guarded_call(label: str, method: str, call: Callable[..., Any], *args: Any,
                 budget_s: float | None = None) -> tuple[Any, float]:
    """``call(*args)`` and its duration [s]. An exception becomes a ControllerError naming the
    controller and the method; so does a call that took longer than ``budget_s``."""
    start = time.perf_counter()
    try:
        result = call(*args)
    except HilError:
        raise
    except Exception as exc:
        raise ControllerError(f"controller {label!r} raised in {method}(): "
                              f"{describe_exception(exc)}") from exc
    elapsed = time.perf_counter() - start
    if budget_s is not None and elapsed > budget_s:
        raise ControllerError(f"controller {label!r} took {elapsed:.3g} s in {method}(), over "
                              f"its budget of {budget_s:g} s (--controller-budget)")
    return result, elapsed
