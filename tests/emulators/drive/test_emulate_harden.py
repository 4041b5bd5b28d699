"""`hil emulate drive` and `hil emulate bench` serve as real-time processes where the OS
allows, by default (`--no-harden`: an ordinary process), and say what they were granted, step
by step, before they are ready, and in a warning what they were not: the bench below hil's
loop on a core apart from the loop's, the drive above it on the loop's core, where it answers
each SYNC before the loop goes on; locked memory. The drive emulator is an ordinary process
while a lockstep master keeps its time."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.core.realtime import (
    ANSWER_PRIORITY,
    HELPER_PRIORITY,
    Hardening,
    helper_metadata,
    loop_cpu,
    parse_step_lines,
)
from hil.emulator_process import start_bench_emulator, start_drive_emulator
from hil.servo.config import load_drive_config
from hil.servo.rig import open_drive, share_lockstep_time
from hil.servo.settings import lockstep_over_a_bus

pytestmark = [pytest.mark.slow]

REPO = Path(__file__).resolve().parents[3]
STEPS = ["sched_fifo", "cpu_affinity", "mlockall", "gc_freeze", "timer_slack"]


def emulate(tmp_path: Path, *argv: str, prefix: tuple[str, ...] = ()) -> subprocess.Popen:
    """``hil emulate ...`` in a process of its own (``prefix``: a command it runs under)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([*prefix, sys.executable, "-m", "hil", "emulate", *argv],
                            cwd=tmp_path, env=env, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)


def stop(emulator: subprocess.Popen) -> str:
    """Stop it; its stderr."""
    emulator.terminate()
    return emulator.communicate(timeout=30)[1]


def test_the_command_hardens_by_default_and_reports_every_step_before_its_ready_line(
        tmp_path):
    emulator = emulate(tmp_path, "drive", "--socketcand", "127.0.0.1:0")
    try:
        assert emulator.stdout is not None
        ready = emulator.stdout.readline()
        assert "on socketcand 127.0.0.1:" in ready
        pid = emulator.pid
        policy, cores = os.sched_getscheduler(pid), os.sched_getaffinity(pid)
        priority = os.sched_getparam(pid).sched_priority
    finally:
        stderr = stop(emulator)
    steps = parse_step_lines(stderr.splitlines())
    assert list(steps) == STEPS, stderr
    assert steps["gc_freeze"].startswith("granted: ") and "collector on" in steps["gc_freeze"]
    if steps["sched_fifo"].startswith("granted"):  # what it says is what it got
        assert (policy, priority) == (os.SCHED_FIFO, ANSWER_PRIORITY)
    usable = sorted(os.sched_getaffinity(0))
    if steps["cpu_affinity"].startswith("granted"):  # the loop's core: it answers there
        assert cores == {loop_cpu(usable)}
        assert steps["cpu_affinity"].endswith("the loop's: it answers within the loop's tick")
    else:
        assert len(usable) < 2 or not steps["sched_fifo"].startswith("granted")


def test_a_started_emulator_reports_what_it_was_granted_for_the_next_session():
    with start_drive_emulator(harden=True) as emulator:
        assert list(emulator.hardening) == STEPS
        assert helper_metadata()["realtime.emulator"] == {"pid": str(emulator.pid),
                                                          **emulator.hardening}
    assert "realtime.emulator" not in helper_metadata()  # stopped: no longer recorded
    with start_drive_emulator() as plain:  # not asked: nothing to report, nothing recorded
        assert plain.hardening == {} and "realtime.emulator" not in helper_metadata()


def test_doctor_says_what_an_emulator_would_be_granted(tmp_path):
    out = subprocess.run([sys.executable, "-m", "hil", "doctor", "--duration", "0.1", "--json"],
                         cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(REPO)},
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    helper = report["emulator_hardening"]
    assert list(helper) == STEPS
    if helper["sched_fifo"]["granted"]:
        assert helper["sched_fifo"]["detail"] == f"priority {ANSWER_PRIORITY}"
    if helper["cpu_affinity"]["granted"] and report["hardening"]["cpu_affinity"]["granted"]:
        # the loop's core, named
        assert helper["cpu_affinity"]["detail"].startswith(
            f"on CPU {report['os']['usable_cpus'][-1]} of ")
        assert "the loop's: it answers within the loop's tick" in helper["cpu_affinity"]["detail"]


def test_no_harden_serves_as_an_ordinary_process(tmp_path):
    emulator = emulate(tmp_path, "drive", "--socketcand", "127.0.0.1:0", "--no-harden")
    try:
        assert emulator.stdout is not None
        assert "on socketcand 127.0.0.1:" in emulator.stdout.readline()
        assert os.sched_getscheduler(emulator.pid) == os.SCHED_OTHER
    finally:
        stderr = stop(emulator)
    assert parse_step_lines(stderr.splitlines()) == {} and "warning" not in stderr


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None,
                    reason="needs root and setpriv to take the real-time capabilities away")
def test_what_the_machine_refuses_is_said_in_a_warning(tmp_path):
    # without CAP_SYS_NICE and CAP_IPC_LOCK, as an ordinary user: no SCHED_FIFO, and the
    # memory lock above the 8 MiB limit
    drop = ("setpriv", "--inh-caps=-sys_nice,-ipc_lock", "--bounding-set=-sys_nice,-ipc_lock")
    emulator = emulate(tmp_path, "drive", "--socketcand", "127.0.0.1:0", prefix=drop)
    try:
        assert emulator.stdout is not None
        assert "on socketcand 127.0.0.1:" in emulator.stdout.readline()
    finally:
        stderr = stop(emulator)
    steps = parse_step_lines(stderr.splitlines())
    assert steps["sched_fifo"].startswith("refused: ")
    warning = next(line for line in stderr.splitlines() if line.startswith("hil: warning: "))
    refused = [name for name, outcome in steps.items() if outcome.startswith("refused")]
    assert warning.startswith(f"hil: warning: the drive emulator serves without "
                              f"{', '.join(refused)} (refused, above): ")


def test_the_drive_emulator_is_an_ordinary_process_while_a_lockstep_master_keeps_its_time():
    with start_drive_emulator(harden=True) as emulator:
        if not emulator.hardening["sched_fifo"].startswith("granted"):
            pytest.skip("SCHED_FIFO is not granted here: nothing to give up")
        assert os.sched_getscheduler(emulator.pid) == os.SCHED_FIFO
        master = open_drive(emulator.url, lockstep_over_a_bus(load_drive_config()))
        try:
            assert share_lockstep_time(master)
            master.sdo.read_int(0x1000, 0)  # a frame: its next service sees the master's time
            # SCHED_OTHER and every core: two calls of the emulator's, waited for together
            assert wait_for(lambda: os.sched_getscheduler(emulator.pid) == os.SCHED_OTHER
                            and os.sched_getaffinity(emulator.pid) == os.sched_getaffinity(0))
        finally:
            master.close()  # lets the time go (0x2005 = 0): the drive's own clock again
        assert wait_for(lambda: os.sched_getscheduler(emulator.pid) == os.SCHED_FIFO)


def test_the_bench_emulator_hardens_its_serving_threads(tmp_path):
    emulator = emulate(tmp_path, "bench", "--tcp", "127.0.0.1:0")
    try:
        assert emulator.stdout is not None
        assert "listening on modbus-tcp://127.0.0.1:" in emulator.stdout.readline()
        threads = [int(tid) for tid in os.listdir(f"/proc/{emulator.pid}/task")]
        fifo = [tid for tid in threads if os.sched_getscheduler(tid) == os.SCHED_FIFO]
    finally:
        stderr = stop(emulator)
    steps = parse_step_lines(stderr.splitlines())
    assert list(steps) == STEPS
    if steps["sched_fifo"].startswith("granted"):  # hardened before its threads started: the
        # main thread, the plant's and the server's (not the watcher of its parent, older)
        assert emulator.pid in fifo and len(fifo) >= 3
        assert steps["sched_fifo"] == f"granted: priority {HELPER_PRIORITY}"  # below the loop
    with start_bench_emulator() as plain:  # the API's default: an ordinary process
        assert plain.hardening == {} and os.sched_getscheduler(plain.pid) == os.SCHED_OTHER


@pytest.mark.realtime
def test_a_hardened_loop_finds_each_answer_when_its_send_returns():
    """The hand-over on the loop's core: the master's SYNC wakes the emulator there, above
    the loop, which answers before the loop's send returns; no SYNC waits for the core to
    come free. The master looks for the TPDOs 1 us after each SYNC: an emulator on a core of
    its own answers 30 us or more after the SYNC, and every cycle would be stale."""
    usable = sorted(os.sched_getaffinity(0))
    if os.geteuid() != 0 or len(usable) < 2:
        pytest.skip("needs SCHED_FIFO (root) and two usable cores")
    with start_drive_emulator(harden=True) as emulator:
        master = open_drive(emulator.url, load_drive_config(overrides={"master": {
            "rx_timeout_us": 1, "stale_cycles": 100_000}}))
        loop = Hardening()
        try:
            master.start()
            loop.apply()
            assert loop.pinned_cpu == loop_cpu(usable)
            stale = 0
            for _ in range(2000):
                master.send_set_point(0.0)
                stale += not master.receive_feedback().fresh
        finally:
            loop.restore()
            master.close()
    assert stale == 0


def wait_for(predicate, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.01)
    return predicate()
