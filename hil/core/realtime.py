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

A helper process that stands in for hardware (``hil emulate bench --harden``, started for a
``--realtime`` bench run against its emulator) takes the same steps as a *helper*
(:meth:`Hardening.for_helper`): SCHED_FIFO at :data:`HELPER_PRIORITY` (below the loop's; not
taken on a single usable CPU, where it would starve the loop's recording), pinned to the core
before the loop's (:func:`helper_cpu`), its collector frozen but kept on (it serves for as
long as it is asked). It reports each step on a line of its stderr
(:func:`step_line`); the run records them as ``realtime.emulator`` metadata
(:func:`report_helper_hardening`, :func:`helper_metadata`).

A helper that answers the loop's frames within its tick, as a drive answers a SYNC
(:meth:`Hardening.for_answering_helper`: ``hil emulate drive --harden`` over socketcand, and
the drive emulator process of a ``--realtime`` servo run), takes the loop's core instead,
at :data:`ANSWER_PRIORITY`, above the loop's: the loop's send makes it runnable there and it
answers at once, before the loop goes on, and before the core can go to any ordinary process.
On a core of its own it waits for the next SYNC with its core idle, and an ordinary process
given that core keeps it for as long as its system call lasts: a kernel without full
preemption (``Dynamic Preempt: none``) does not take the core back for a real-time thread
whose wake-up came meanwhile. On the 2-core virtual machine this was measured on, the VM's
agent takes an idle core once a second, for 0.5-1.5 ms at a time: one SYNC a second was
answered too late (stale feedback, late frames).
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import os
import platform
import resource
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hil.core.libc import libc as c_library

PR_SET_TIMERSLACK = 29
PR_GET_TIMERSLACK = 30
MCL_CURRENT, MCL_FUTURE = 1, 2
DEFAULT_PRIORITY = 80  # below the kernel's threaded IRQs (50) would starve the NIC; above is usual
#: an emulator standing in for hardware: real time too, below the loop (on one CPU the loop wins)
HELPER_PRIORITY = DEFAULT_PRIORITY - 10
#: an emulator answering within the loop's tick, on the loop's core: above the loop, which its
#: answers interrupt for tens of microseconds
ANSWER_PRIORITY = DEFAULT_PRIORITY + 5
#: the prefix of a helper's lines that report its hardening steps (on its stderr)
STEP_PREFIX = "hil: real-time: "


@dataclass(frozen=True)
class Step:
    """One hardening step: whether the OS granted it, and what happened."""

    name: str
    granted: bool
    detail: str


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
    libc = c_library()
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


def loop_cpu(usable: list[int]) -> int | None:
    """The core a hardened loop thread takes: the last usable one (None: fewer than two)."""
    return usable[-1] if len(usable) >= 2 else None


def helper_cpu(usable: list[int]) -> int | None:
    """The core a hardened helper (an emulator) takes: the one before the loop's, so that the
    two never compete (None: fewer than two usable cores)."""
    return usable[-2] if len(usable) >= 2 else None


@dataclass
class HelperProcess:
    """A process that serves the run (an emulator standing in for hardware) and, once it
    reported them, its hardening steps (``{step: "granted: ..." | "refused: ..."}``)."""

    pid: int
    name: str
    steps: dict[str, str] = field(default_factory=dict)


_HELPERS: dict[int, HelperProcess] = {}


def register_helper_process(pid: int, name: str = "emulator") -> None:
    """A process that serves this run (an emulator standing in for hardware): hardening keeps
    it off the loop's core. :func:`forget_helper_process` when it stops."""
    _HELPERS.setdefault(pid, HelperProcess(pid, name))


def report_helper_hardening(pid: int, steps: dict[str, str]) -> None:
    """What a registered helper process was granted (its :func:`parse_step_lines`), recorded
    by the next real-time session as ``realtime.<name>`` metadata."""
    helper = _HELPERS.get(pid)
    if helper is not None:
        helper.steps = dict(steps)


def forget_helper_process(pid: int) -> None:
    _HELPERS.pop(pid, None)


def helper_metadata() -> dict[str, dict[str, str]]:
    """``{"realtime.<name>": {"pid": ..., step: outcome}}`` of every helper that reported its
    hardening: the session's metadata records beside the loop's ``realtime``."""
    return {f"realtime.{helper.name}": {"pid": str(helper.pid), **helper.steps}
            for helper in _HELPERS.values() if helper.steps}


def step_line(step: Step) -> str:
    """One hardening step as a helper reports it: ``hil: real-time: NAME granted: DETAIL``."""
    return f"{STEP_PREFIX}{step.name} {'granted' if step.granted else 'refused'}: {step.detail}"


def parse_step_lines(lines: list[str]) -> dict[str, str]:
    """``{step: "granted: ..." | "refused: ..."}`` from a helper's :func:`step_line` lines
    (other lines are skipped)."""
    steps = {}
    for line in lines:
        if line.startswith(STEP_PREFIX):
            name, _, outcome = line.removeprefix(STEP_PREFIX).strip().partition(" ")
            if outcome.startswith(("granted: ", "refused: ")):
                steps[name] = outcome
    return steps


def keep_process_off_cpu(pid: int, cpu: int) -> bool:
    """Move every thread of process ``pid`` off ``cpu`` (threads it starts later inherit the
    affinity of the thread that starts them), but for a thread pinned to ``cpu`` alone (an
    answering helper's serving thread). False when no thread was moved."""
    if not hasattr(os, "sched_setaffinity"):
        return False
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:
        tids = [pid]
    moved = False
    for tid in tids:
        try:
            others = os.sched_getaffinity(tid) - {cpu}
            if others:
                os.sched_setaffinity(tid, others)
                moved = True
        except OSError:  # the thread ended meanwhile, or we may not touch it
            continue
    return moved


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
    affinity, the collector, the timer slack and the locked pages back.
    A loop (the default) takes the last core and keeps the registered helper processes off it
    (but for a thread that answers on it), and holds the collector off; a helper
    (:meth:`for_helper`) takes the core before it, an answering helper
    (:meth:`for_answering_helper`) the loop's core, and both keep their collector on.
    """

    def __init__(self, priority: int = DEFAULT_PRIORITY, pin: bool = True, *,
                 helper: bool = False, answering: bool = False) -> None:
        self.priority = priority
        self.pin = pin
        self.helper = helper or answering
        self.answering = answering
        self.steps: list[Step] = []
        self._saved_policy: tuple[int, int] | None = None
        self._saved_affinity: set[int] | None = None
        self.pinned_cpu: int | None = None  # the thread's core, once pinned
        self._saved_slack: int | None = None
        self._gc_was_enabled = False
        self._locked = False  # mlockall granted: munlockall at restore

    @classmethod
    def for_helper(cls) -> Hardening:
        """The hardening of a process standing in for hardware (an emulator): real time below
        the loop, on a core apart from the loop's."""
        return cls(HELPER_PRIORITY, helper=True)

    @classmethod
    def for_answering_helper(cls) -> Hardening:
        """The hardening of an emulator that answers the loop's frames within its tick (a
        drive answering SYNC): real time above the loop, on the loop's core."""
        return cls(ANSWER_PRIORITY, answering=True)

    @property
    def real_time(self) -> bool:
        """Whether the thread is on SCHED_FIFO now (applied and granted, not restored)."""
        return self._saved_policy is not None

    def apply(self) -> list[Step]:
        # the slow steps first (locking the pages of a process takes 0.2 s), before the thread
        # is real-time: an answering helper would take them out of the loop's core
        locked, frozen = self._mlockall(), self._gc()
        self.steps = [self._fifo(), self._affinity(), locked, frozen, self._slack()]
        return self.steps

    def _fifo(self) -> Step:
        if not hasattr(os, "SCHED_FIFO"):
            return Step("sched_fifo", False, "not available on this platform")
        usable = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        if self.helper and helper_cpu(usable) is None:  # it would starve the loop's recording
            return Step("sched_fifo", False, f"not taken: only CPU {usable} usable, the loop's")
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
        if self.answering and not self.real_time:
            return Step("cpu_affinity", False, "not taken without SCHED_FIFO: on the loop's "
                        "core it would answer only while the loop sleeps")
        core = (helper_cpu if self.helper and not self.answering else loop_cpu)(usable)
        if core is None:
            return Step("cpu_affinity", False, f"only CPU {usable} usable: nothing to pin to")
        try:
            self._saved_affinity = set(usable)
            os.sched_setaffinity(0, {core})
        except OSError as exc:
            self._saved_affinity = None
            return Step("cpu_affinity", False, f"refused: {exc.strerror or exc}")
        self.pinned_cpu = core
        if self.answering:
            return Step("cpu_affinity", True, f"on CPU {core} of {usable}, the loop's: it "
                        "answers within the loop's tick")
        if self.helper:
            return Step("cpu_affinity", True, f"on CPU {core} of {usable}, apart from the "
                        f"loop's CPU {loop_cpu(usable)}")
        moved = [pid for pid in sorted(_HELPERS) if keep_process_off_cpu(pid, core)]
        helpers = f"; helper process(es) {moved} kept off it (a thread answering within the " \
            "tick stays)" if moved else ""
        return Step("cpu_affinity", True, f"loop thread on CPU {core} of {usable}{helpers}")

    def _mlockall(self) -> Step:
        libc = c_library()
        if libc is None or not sys.platform.startswith("linux"):
            return Step("mlockall", False, "no libc mlockall on this platform")
        if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
            errno = ctypes.get_errno()
            return Step("mlockall", False, f"refused: {os.strerror(errno)} (memlock limit "
                        f"{_limit(resource.RLIMIT_MEMLOCK)} bytes)")
        self._locked = True
        return Step("mlockall", True, "current and future pages locked")

    def _gc(self) -> Step:
        self._gc_was_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()
        if self.helper:  # it serves for as long as it is asked: cycles must still be freed
            return Step("gc_freeze", True, f"collected, {gc.get_freeze_count()} objects "
                        "frozen, collector on (it scans only what came later)")
        gc.disable()
        return Step("gc_freeze", True, f"collected, {gc.get_freeze_count()} objects frozen, "
                    "collector off during the run")

    def _slack(self) -> Step:
        libc = c_library()
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
            libc = c_library()
            if libc is not None:
                libc.prctl(PR_SET_TIMERSLACK, self._saved_slack, 0, 0, 0)
            self._saved_slack = None
        libc = c_library()
        if self._locked and libc is not None:
            libc.munlockall()
            self._locked = False
        gc.unfreeze()
        if self._gc_was_enabled:
            gc.enable()

    def as_metadata(self) -> dict[str, str]:
        """``{step: "granted: ..." | "refused: ..."}`` for a session's metadata record."""
        return {s.name: ("granted: " if s.granted else "refused: ") + s.detail
                for s in self.steps}
