"""`hil emulate drive --harden`: the emulator serves as a real-time process where the OS
allows (SCHED_FIFO below hil's loop, a core apart from the loop's, locked memory) and says
what it was granted, step by step, before it is ready."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hil.core.realtime import HELPER_PRIORITY, helper_metadata, loop_cpu, parse_step_lines
from hil.emulator_process import start_drive_emulator

pytestmark = [pytest.mark.slow]

REPO = Path(__file__).resolve().parents[3]
STEPS = ["sched_fifo", "cpu_affinity", "mlockall", "gc_freeze", "timer_slack"]


def test_the_command_reports_every_step_before_its_ready_line(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    emulator = subprocess.Popen(
        [sys.executable, "-m", "hil", "emulate", "drive", "--socketcand", "127.0.0.1:0",
         "--harden"], cwd=tmp_path, env=env, text=True, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE)
    try:
        assert emulator.stdout is not None
        ready = emulator.stdout.readline()
        assert "on socketcand 127.0.0.1:" in ready
        pid = emulator.pid
        policy, cores = os.sched_getscheduler(pid), os.sched_getaffinity(pid)
        priority = os.sched_getparam(pid).sched_priority
    finally:
        emulator.terminate()
        _, stderr = emulator.communicate(timeout=30)
    steps = parse_step_lines(stderr.splitlines())
    assert list(steps) == STEPS, stderr
    assert steps["gc_freeze"].startswith("granted: ") and "collector on" in steps["gc_freeze"]
    if steps["sched_fifo"].startswith("granted"):  # what it says is what it got
        assert (policy, priority) == (os.SCHED_FIFO, HELPER_PRIORITY)
    usable = sorted(os.sched_getaffinity(0))
    if steps["cpu_affinity"].startswith("granted"):
        assert len(cores) == 1 and loop_cpu(usable) not in cores
    else:
        assert len(usable) < 2 or "refused" in steps["cpu_affinity"]


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
        assert helper["sched_fifo"]["detail"] == f"priority {HELPER_PRIORITY}"
    if helper["cpu_affinity"]["granted"] and report["hardening"]["cpu_affinity"]["granted"]:
        # the two cores named: the emulator's apart from the loop's
        assert f"apart from the loop's CPU {report['os']['usable_cpus'][-1]}" in \
            helper["cpu_affinity"]["detail"]
