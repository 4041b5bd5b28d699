"""A hil process runs numpy's and scipy's BLAS on one thread, unless its user set
``OPENBLAS_NUM_THREADS``: ``hil.cli.main.main`` sets it before a command imports numpy (the
hardware guide, "Real hardware and real time"). Run from a folder outside the repository."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow  # each test starts a process

#: main as the ``hil`` command runs it, then numpy and scipy.linalg imported as a command does:
#: the variable as the process has it, and the threads the process then has
PROGRAM = """
import os
from hil.cli.main import main
try:
    main(["--version"])
except SystemExit:
    pass
import numpy, scipy.linalg
numpy.ones((64, 64)) @ numpy.ones((64, 64))
print(os.environ.get("OPENBLAS_NUM_THREADS"), len(os.listdir("/proc/self/task")))
"""


def _threads(tmp_path, **env: str) -> tuple[str, int]:
    clean = {key: value for key, value in os.environ.items()
             if key not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "GOTO_NUM_THREADS")}
    done = subprocess.run([sys.executable, "-c", PROGRAM], cwd=tmp_path, env={**clean, **env},
                          capture_output=True, text=True, timeout=60, check=True)
    setting, threads = done.stdout.splitlines()[-1].split()  # after "hil VERSION"
    return setting, int(threads)


def test_a_hil_process_runs_blas_on_one_thread(tmp_path):
    assert _threads(tmp_path) == ("1", 1)


def test_the_users_own_setting_stands(tmp_path):
    setting, threads = _threads(tmp_path, OPENBLAS_NUM_THREADS="2")
    assert setting == "2"
    assert threads >= min(2, len(os.sched_getaffinity(0)))  # OpenBLAS takes at most a core each
