"""A veth pair in a network namespace of its own: where an EtherCAT master and hil's slave meet
with real Ethernet frames and no NIC (the tests, the benchmarks, a first try without hardware),
and nothing touches a real interface. Making one needs root (CAP_NET_ADMIN) and iproute2's
``ip``; :func:`missing` says why it cannot be made here.

:func:`veth_pair` makes the namespace and the pair (both ends up) and removes them afterwards;
:func:`inside` moves the calling thread into the namespace (``setns``: a raw socket opened
there stays there, a process started from it runs there); :meth:`Veth.command` runs a command
in it (``ip netns exec``)."""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import subprocess
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass

from hil.emulators.errors import EmulatorError

CLONE_NEWNET = 0x4000_0000


def missing() -> str | None:
    """Why this machine cannot make a network namespace here (None: it can)."""
    if os.geteuid() != 0:
        return "needs root (CAP_NET_ADMIN, CAP_NET_RAW) to make a network namespace and a veth"
    if shutil.which("ip") is None:
        return "needs iproute2's `ip` to make a network namespace and a veth pair"
    return None


@dataclass(frozen=True)
class Veth:
    """A namespace ``ns`` holding a veth pair: the ``master`` end and the ``slave`` end."""

    ns: str
    master: str
    slave: str

    def ip(self, *argv: str) -> None:
        """``ip -n NS ARGV``; a refusal is an EmulatorError with what ``ip`` said."""
        done = subprocess.run(["ip", "-n", self.ns, *argv], capture_output=True, text=True,
                              timeout=30)
        if done.returncode:
            raise EmulatorError(f"ip -n {self.ns} {' '.join(argv)}: {done.stderr.strip()}")

    def set_down(self, end: str) -> None:
        self.ip("link", "set", end, "down")

    def command(self, *argv: str) -> list[str]:
        """``argv`` run inside the namespace."""
        return ["ip", "netns", "exec", self.ns, *argv]


@contextlib.contextmanager
def veth_pair(prefix: str = "hil-ecat") -> Iterator[Veth]:
    """A fresh namespace with a veth pair, both ends up (their names unique: a run locks its
    segment by name); removed afterwards."""
    reason = missing()
    if reason is not None:
        raise EmulatorError(f"cannot make a veth pair: {reason}")
    suffix = uuid.uuid4().hex[:8]
    veth = Veth(f"{prefix}-{os.getpid()}-{suffix}", f"em{suffix}", f"es{suffix}")
    made = subprocess.run(["ip", "netns", "add", veth.ns], capture_output=True, text=True,
                          timeout=30)
    if made.returncode:
        raise EmulatorError(f"cannot make a network namespace: {made.stderr.strip()}")
    try:
        veth.ip("link", "add", veth.master, "type", "veth", "peer", "name", veth.slave)
        for end in ("lo", veth.master, veth.slave):
            veth.ip("link", "set", end, "up")
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
            raise EmulatorError(f"cannot enter namespace {veth.ns}: "
                                f"{os.strerror(ctypes.get_errno())}")
        try:
            yield
        finally:
            if libc.setns(own, CLONE_NEWNET):
                raise EmulatorError("cannot leave the namespace "
                                    f"{veth.ns}: {os.strerror(ctypes.get_errno())}")
    finally:
        os.close(own)
        os.close(target)
