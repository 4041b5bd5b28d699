"""A silent HiGHS instance.

HiGHS 1.16 prints its banner on standard output from the constructor of a process's first
instance, before any option can be set; on ``hil ... --json`` that line would break the JSON a
script reads. The constructor therefore runs with file descriptor 1 pointed at /dev/null.
"""

from __future__ import annotations

import os
import sys

import highspy


def silent_highs() -> highspy.Highs:
    """``highspy.Highs()`` with its banner swallowed and its output switched off."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        highs = highspy.Highs()
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)
    highs.silent()
    return highs
