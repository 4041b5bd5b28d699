"""hil.core.libc: the process's C library, found once, and the kernel's signal to a process
whose parent ends (what helper processes and the local lab's daemons rely on)."""

import subprocess
import sys
import textwrap
import time

import pytest

from hil.core.libc import libc

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl is Linux's")

# the parent starts a child that asks for SIGTERM at its parent's end, tells its pid, then ends
PARENT = textwrap.dedent("""
    import subprocess, sys
    child = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE, text=True)
    print(child.stdout.readline().strip(), flush=True)
""")
CHILD = textwrap.dedent("""
    import os, time
    from hil.core.libc import die_with_parent_signal
    assert die_with_parent_signal()
    print(os.getpid(), flush=True)
    time.sleep(60)
""")


def test_the_library_is_found_once_and_answers():
    assert libc() is libc()
    assert libc().getpid() == __import__("os").getpid()


def test_a_child_that_asked_ends_with_its_parent():
    parent = subprocess.run([sys.executable, "-c", f"CHILD = {CHILD!r}\n{PARENT}"],
                            capture_output=True, text=True, timeout=60, check=True)
    child = int(parent.stdout)
    deadline = time.monotonic() + 30  # a bound on the wait, not a measured figure
    while _alive(child) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not _alive(child), "the child outlived its parent"


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False
