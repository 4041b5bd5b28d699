"""EtherCAT over a veth pair in a network namespace of the test's own: nothing touches a real
interface. :func:`veth_pair` makes the namespace and the pair (``ip netns``, root) and removes
them after; :func:`inside` moves the calling thread into the namespace (``setns``: a raw socket
opened there, pysoem's, stays there; a process started from it runs there); hil's EtherCAT
slave is started on one end as ``hil emulate drive --ethercat`` (:func:`start_slave`), the
master opens the other.

A test that cannot make a namespace (no root, no ``ip``) is skipped with the reason."""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CLONE_NEWNET = 0x4000_0000


def missing() -> str | None:
    """Why this machine cannot make a network namespace for a test (None: it can)."""
    if os.geteuid() != 0:
        return "needs root (CAP_NET_ADMIN, CAP_NET_RAW) to make a network namespace and a veth"
    if shutil.which("ip") is None:
        return "needs iproute2's `ip` to make a network namespace and a veth pair"
    return None


@dataclass(frozen=True)
class Veth:
    """A namespace ``ns`` holding a veth pair: ``master`` end and ``slave`` end."""

    ns: str
    master: str
    slave: str

    def run(self, *argv: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        return subprocess.run(["ip", "-n", self.ns, *argv], check=check, capture_output=True,
                              text=True, timeout=30)

    def set_down(self, end: str) -> None:
        self.run("link", "set", end, "down")


@contextlib.contextmanager
def veth_pair() -> Iterator[Veth]:
    """A fresh namespace with a veth pair, both ends up; removed afterwards."""
    reason = missing()
    if reason is not None:
        pytest.skip(reason)
    suffix = uuid.uuid4().hex[:8]  # the ends' names too: a run locks its segment by name
    veth = Veth(f"hil-ecat-{os.getpid()}-{suffix}", f"em{suffix}", f"es{suffix}")
    made = subprocess.run(["ip", "netns", "add", veth.ns], capture_output=True, text=True,
                          timeout=30)
    if made.returncode:
        pytest.skip(f"cannot make a network namespace: {made.stderr.strip()}")
    try:
        veth.run("link", "add", veth.master, "type", "veth", "peer", "name", veth.slave)
        for end in ("lo", veth.master, veth.slave):
            veth.run("link", "set", end, "up")
        yield veth
    finally:
        subprocess.run(["ip", "netns", "delete", veth.ns], capture_output=True, timeout=30)


@contextlib.contextmanager
def inside(veth: Veth) -> Iterator[None]:
    """The calling thread in ``veth``'s namespace, and back in its own afterwards."""
    libc = ctypes.CDLL(None, use_errno=True)
    own = os.open(f"/proc/self/task/{threading.get_native_id()}/ns/net", os.O_RDONLY)
    target = os.open(f"/run/netns/{veth.ns}", os.O_RDONLY)
    try:
        if libc.setns(target, CLONE_NEWNET):
            raise OSError(ctypes.get_errno(), f"setns into {veth.ns}")
        try:
            yield
        finally:
            if libc.setns(own, CLONE_NEWNET):
                raise OSError(ctypes.get_errno(), "setns back")
    finally:
        os.close(own)
        os.close(target)


def start_slave(veth: Veth, *args: str) -> subprocess.Popen[str]:
    """``hil emulate drive --ethercat SLAVE-END ARGS`` in the namespace, once it says it is
    ready (a bounded wait)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        ["ip", "netns", "exec", veth.ns, sys.executable, "-m", "hil", "emulate", "drive",
         "--ethercat", veth.slave, *args],
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
def slave_on(veth: Veth, *args: str) -> Iterator[subprocess.Popen[str]]:
    proc = start_slave(veth, *args)
    try:
        yield proc
    finally:
        stop_slave(proc)
