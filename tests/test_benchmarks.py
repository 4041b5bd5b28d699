"""Benchmarks that cannot rot: every script in benchmarks/ imports (``make check`` runs this),
so a name that moves in the code under them fails here, not on the next ``make bench``; and
every script runs end to end in its seconds-long ``--quick`` mode (``make test``), so a call
that no longer fits, a run that fails or a figure that no longer prints fails here too. Only
that it ran and printed figures is checked, never their values: this machine is shared."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = sorted((ROOT / "benchmarks").glob("*.py"))
# a figure: a decimal number, a ratio (3.2x) or a share (12 %)
FIGURE = re.compile(r"\d\.\d|\d+x\b|\d ?%")


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda path: path.stem)
def test_every_benchmark_imports(script: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    name = f"benchmark_{script.stem}"
    spec = importlib.util.spec_from_file_location(name, script)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, name, module)  # dataclasses look their module up
    monkeypatch.syspath_prepend(str(script.parent))  # as `python benchmarks/X.py` runs it
    spec.loader.exec_module(module)
    assert callable(getattr(module, "main", None)), f"{script.name} has no main()"


#: what a script's --quick must print besides a figure: the lines of the paths its quick run
#: folds into fewer runs (a run that no longer reaches one fails here, not on `make bench`);
#: none that a loaded machine's pace decides (a client that connected in time, say)
QUICK_LINES = {
    "compare": ("hil compare", "hil report", "hil export", "compare / report"),
    "ethercat": ("CAN (socketcand)",),
    "faults": ("the final 'silent' fault:", "bench over a noisy RTU line"),
    "fuzz": ("cases in",),
    "lab": ("--bench URL", "--place adds", "importing labgrid"),
    "modbus": ("TCP hil driver", "RTU pty: hil driver", "RTU pty paced at 115200 8N1: hil driver",
               "TCP emulator process", "RTU paced 115200", "TCP  after", "RTU  after"),
    "realtime": ("hops of a wire run's cycles", "lockstep servo through the CAN link",
                 "real-time bench"),
    "session_start": ("hil servo run --controller pid --duration 0.1, start to end",),
    "servo": ("max |u_fast - u_cvxpy|", "lockstep MPC FOH H_t = H_u = 8", "MPC through CAN"),
    "tune": ("MPC, controller.hp changed", "skipped share: MPC"),
}


#: the scripts whose --quick drives an axis in real time at 2 kHz, its safety on: run with the
#: other real-time tests, ahead of the niced rest (beside 3 workers at the same priority a late
#: loop stopped one on its velocity limit)
REAL_TIME = {"servo", "ethercat"}


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("script", [
    pytest.param(path, marks=pytest.mark.realtime) if path.stem in REAL_TIME else path
    for path in BENCHMARKS], ids=lambda path: path.stem)
def test_every_benchmark_runs_quick(script: Path) -> None:
    # as `make bench` runs it, from the checkout, only shorter
    done = subprocess.run([sys.executable, str(script), "--quick"], cwd=ROOT,
                          capture_output=True, text=True, timeout=280, stdin=subprocess.DEVNULL,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert done.returncode == 0, f"{script.name} --quick exited {done.returncode}:\n" \
                                 f"{done.stdout[-2000:]}\n{done.stderr[-3000:]}"
    figures = [line for line in done.stdout.splitlines() if FIGURE.search(line)]
    assert figures, f"{script.name} --quick printed no figure:\n{done.stdout[-2000:]}"
    missing = [line for line in QUICK_LINES.get(script.stem, ()) if line not in done.stdout]
    assert not missing, f"{script.name} --quick printed none of {missing}:\n{done.stdout[-3000:]}"
