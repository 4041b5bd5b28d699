"""What the operating system grants a real-time loop, and the hardening steps that use it.

Each hardening step is tried and reported as granted or refused with the reason, never
silently: a session records the list in its metadata, and ``hil doctor`` prints what this
machine grants and what an administrator would change.

Steps (all Linux; elsewhere each is refused with the reason):

* ``sched_fifo`` - the calling (loop) thread on SCHED_FIFO at ``priority``;
* ``cpu_affinity`` - the loop thread pinned to one core, the last one, when there are two or
  more (everything else keeps the other cores);
* ``mlockall`` - current and future memory locked, through ctypes (no page faults mid-loop);
* ``gc_freeze`` - ``gc.collect()`` then ``gc.freeze()``, and the collector held off for the run;
* ``timer_slack`` - the thread's timer slack set to 1 ns (``prctl``), so sleeps end on time.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import gc
import os
import platform
import resource
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

PR_SET_TIMERSLACK = 29
PR_GET_TIMERSLACK = 30
MCL_CURRENT, MCL_FUTURE = 1, 2
DEFAULT_PRIORITY = 80  # below the kernel's threaded IRQs (50) would starve the NIC; above is usual


@dataclass(frozen=True)
class Step:
    """One hardening step: whether the OS granted it, and what happened."""

    name: str
    granted: bool
    detail: str


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name, use_errno=True) if name else None
    except OSError:
        return None


def _read(path: str) -> str | None:
    try:
        return Path(path).read_text().strip()
    except OSError:
        return None


def _limit(which: int) -> str:
    soft, _hard = resource.getrlimit(which)
    return "unlimited" if soft == resource.RLIM_INFINITY else str(soft)


def timer_slack_ns() -> int | None:
    """The calling thread's timer slack (Linux), or None where it cannot be read."""
    libc = _libc()
    if libc is None or not sys.platform.startswith("linux"):
        return None
    value = libc.prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0)
    return int(value) if value >= 0 else None


def machine_report() -> dict[str, Any]:
    """What this machine grants a real-time loop (``hil doctor``'s ``os`` part)."""
    cpus = os.cpu_count() or 1
    fifo_max = os.sched_get_priority_max(os.SCHED_FIFO) if hasattr(os, "SCHED_FIFO") else 0
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "implementation": platform.python_implementation(),
        "cpus": cpus,
        "usable_cpus": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
        else list(range(cpus)),
        "isolated_cpus": _read("/sys/devices/system/cpu/isolated") or "",
        "sched_fifo_max_priority": fifo_max,
        "rtprio_limit": _limit(resource.RLIMIT_RTPRIO) if hasattr(resource, "RLIMIT_RTPRIO")
        else "n/a",
        "root": os.geteuid() == 0 if hasattr(os, "geteuid") else False,
        "memlock_limit_bytes": _limit(resource.RLIMIT_MEMLOCK),
        "timer_slack_ns": timer_slack_ns(),
        "cpu_governor": _read("/sys/devices/system/cpu/cpu0/cpufreq/scaling_governor")
        or "unknown (no cpufreq)",
        "preempt_rt": _read("/sys/kernel/realtime") == "1" or "PREEMPT_RT" in platform.version(),
    }


def advice(report: dict[str, Any], steps: list[Step]) -> list[str]:
    """What an administrator would change on this machine, one line each."""
    lines = []
    refused = {s.name: s for s in steps if not s.granted}
    if "sched_fifo" in refused:
        lines.append("allow SCHED_FIFO: run as root, give CAP_SYS_NICE, or raise 'rtprio' in "
                     "/etc/security/limits.conf (ulimit -r)")
    if "mlockall" in refused:
        lines.append("allow mlockall: raise 'memlock' in /etc/security/limits.conf "
                     "(ulimit -l unlimited) or give CAP_IPC_LOCK")
    if not report["isolated_cpus"] and report["cpus"] >= 2:
        lines.append("isolate a core for the loop: boot with isolcpus=N nohz_full=N rcu_nocbs=N")
    governor = str(report["cpu_governor"])
    if governor not in ("performance",) and not governor.startswith("unknown"):
        lines.append(f"CPU frequency governor is '{governor}': set 'performance' "
                     "(cpupower frequency-set -g performance)")
    if not report["preempt_rt"]:
        lines.append("a PREEMPT_RT kernel bounds the worst-case wake-up; this one is not")
    if report["cpus"] < 2:
        lines.append("one CPU: the loop shares it with the recorder and every other process")
    return lines


def ordinary_thread() -> None:
    """Make the calling thread an ordinary one again: SCHED_OTHER on every usable core. For a
    thread started from a hardened loop thread (which it would otherwise inherit), e.g. as a
    ``ThreadPoolExecutor`` initializer."""
    if hasattr(os, "SCHED_OTHER"):
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    if hasattr(os, "sched_setaffinity"):
        with contextlib.suppress(OSError):
            os.sched_setaffinity(0, range(os.cpu_count() or 1))


class Hardening:
    """Applies the hardening steps to the calling thread and undoes what can be undone.

    ``apply()`` returns every step, granted or refused; ``restore()`` puts the scheduler, the
    affinity, the collector and the timer slack back (mlockall stays until the process ends).
    """

    def __init__(self, priority: int = DEFAULT_PRIORITY, pin: bool = True) -> None:
        self.priority = priority
        self.pin = pin
        self.steps: list[Step] = []
        self._saved_policy: tuple[int, int] | None = None
        self._saved_affinity: set[int] | None = None
        self.pinned_cpu: int | None = None  # the loop thread's core, once pinned
        self._saved_slack: int | None = None
        self._gc_was_enabled = False

    def apply(self) -> list[Step]:
        self.steps = [self._fifo(), self._affinity(), self._mlockall(), self._gc(),
                      self._slack()]
        return self.steps

    def _fifo(self) -> Step:
        if not hasattr(os, "SCHED_FIFO"):
            return Step("sched_fifo", False, "not available on this platform")
        try:
            self._saved_policy = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
            priority = min(self.priority, os.sched_get_priority_max(os.SCHED_FIFO))
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except OSError as exc:
            self._saved_policy = None
            return Step("sched_fifo", False, f"refused: {exc.strerror or exc}")
        return Step("sched_fifo", True, f"priority {priority}")

    def _affinity(self) -> Step:
        if not self.pin:
            return Step("cpu_affinity", False, "not asked for")
        if not hasattr(os, "sched_setaffinity"):
            return Step("cpu_affinity", False, "not available on this platform")
        usable = sorted(os.sched_getaffinity(0))
        if len(usable) < 2:
            return Step("cpu_affinity", False, f"only CPU {usable} usable: nothing to pin to")
        core = usable[-1]
        try:
            self._saved_affinity = set(usable)
            os.sched_setaffinity(0, {core})
        except OSError as exc:
            self._saved_affinity = None
            return Step("cpu_affinity", False, f"refused: {exc.strerror or exc}")
        self.pinned_cpu = core
        return Step("cpu_affinity", True, f"loop thread on CPU {core} of {usable}")

    def _mlockall(self) -> Step:
        libc = _libc()
        if libc is None or not sys.platform.startswith("linux"):
            return Step("mlockall", False, "no libc mlockall on this platform")
        if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
            errno = ctypes.get_errno()
            return Step("mlockall", False, f"refused: {os.strerror(errno)} (memlock limit "
                        f"{_limit(resource.RLIMIT_MEMLOCK)} bytes)")
        return Step("mlockall", True, "current and future pages locked")

    def _gc(self) -> Step:
        self._gc_was_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()
        gc.disable()
        return Step("gc_freeze", True, f"collected, {gc.get_freeze_count()} objects frozen, "
                    "collector off during the run")

    def _slack(self) -> Step:
        libc = _libc()
        if libc is None or not sys.platform.startswith("linux"):
            return Step("timer_slack", False, "no prctl on this platform")
        self._saved_slack = timer_slack_ns()
        if libc.prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0) != 0:
            return Step("timer_slack", False, f"refused: {os.strerror(ctypes.get_errno())}")
        return Step("timer_slack", True, f"1 ns (was {self._saved_slack} ns)")

    def restore(self) -> None:
        if self._saved_policy is not None:
            policy, priority = self._saved_policy
            os.sched_setscheduler(0, policy, os.sched_param(priority))
            self._saved_policy = None
        if self._saved_affinity is not None:
            os.sched_setaffinity(0, self._saved_affinity)
            self._saved_affinity = None
        if self._saved_slack is not None:
            libc = _libc()
            if libc is not None:
                libc.prctl(PR_SET_TIMERSLACK, self._saved_slack, 0, 0, 0)
            self._saved_slack = None
        gc.unfreeze()
        if self._gc_was_enabled:
            gc.enable()

    def as_metadata(self) -> dict[str, str]:
        """``{step: "granted: ..." | "refused: ..."}`` for a session's metadata record."""
        return {s.name: ("granted: " if s.granted else "refused: ") + s.detail
                for s in self.steps}
