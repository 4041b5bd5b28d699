"""EtherCAT over a veth pair in a network namespace of the test's own
(:mod:`hil.emulators.ethercat.veth`): :func:`veth_pair` skips the test with the reason where
none can be made; hil's EtherCAT slave is started on one end as ``hil emulate drive
--ethercat`` (:func:`start_slave`), the master opens the other."""

from __future__ import annotations

import contextlib
import os
import re
import select
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from hil.emulators.ethercat import veth
from hil.emulators.ethercat.veth import Veth, inside

REPO = Path(__file__).resolve().parents[1]
__all__ = ["REPO", "Veth", "inside", "slave_on", "start_slave", "stop_slave", "veth_pair"]


@contextlib.contextmanager
def veth_pair() -> Iterator[Veth]:
    """A namespace with a veth pair for this test, removed after it (skipped without root)."""
    reason = veth.missing()
    if reason is not None:
        pytest.skip(reason)
    with veth.veth_pair() as pair:
        yield pair


def start_slave(pair: Veth, *args: str) -> subprocess.Popen[str]:
    """``hil emulate drive --ethercat SLAVE-END ARGS`` in the namespace, once it says it is
    ready (a bounded wait)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        pair.command(sys.executable, "-m", "hil", "emulate", "drive", "--ethercat",
                     pair.slave, *args),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], 60)
    line = proc.stdout.readline() if ready else ""
    if not re.search(r"as EtherCAT slaves? ", line):
        proc.kill()
        _, err = proc.communicate(timeout=10)
        pytest.fail(f"the EtherCAT slave did not start: {line!r} {err!r}")
    return proc


def stop_slave(proc: subprocess.Popen[str]) -> str:
    """Stop it (SIGTERM; resumed first, should a test have frozen it); what it printed."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGCONT)
        proc.terminate()
    try:
        out, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate(timeout=10)
    return out + err


@contextlib.contextmanager
def slave_on(pair: Veth, *args: str) -> Iterator[subprocess.Popen[str]]:
    proc = start_slave(pair, *args)
    try:
        yield proc
    finally:
        stop_slave(proc)


@contextlib.contextmanager
def soem_on(pair: Veth, *slave_args: str) -> Iterator[Any]:
    """hil's slave on ``pair``'s end (``slave_args`` as ``hil emulate drive --ethercat`` takes
    them) and SOEM's master (pysoem: a master hil did not write) opened on the other, in the
    pair's namespace, with SOEM's waits as hil's master sets them (a loaded machine's slave is
    slow)."""
    import pysoem

    from hil.drivers.ethercat.segment import load_pysoem

    load_pysoem()
    with slave_on(pair, *slave_args), inside(pair):
        master = pysoem.Master()
        master.open(pair.master)
        try:
            yield master
        finally:
            master.close()
