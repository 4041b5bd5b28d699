"""``hil doctor`` and the real-time hardening steps, granted or refused, reported either way."""

import gc
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hil.core.realtime import Hardening
from tests.cli import hil_here

pytestmark = [pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
STEPS = ["sched_fifo", "cpu_affinity", "mlockall", "gc_freeze", "timer_slack"]


def test_doctor_json_reports_both_rates_the_os_and_the_hardening():
    out = subprocess.run([sys.executable, "-m", "hil", "doctor", "--duration", "0.3", "--json"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert set(report["loops"]) == {"1000", "2000"}
    for rate, row in report["loops"].items():
        assert set(row) >= {"p50_us", "p99_us", "max_us", "missed_pct"}
        assert 0 <= row["p50_us"] <= row["p99_us"] <= max(row["max_us"], row["p99_us"])
        assert 0 <= row["missed_pct"] <= 100
        assert row["ticks"] == pytest.approx(0.3 * int(rate), rel=0.05)
    assert list(report["hardening"]) == STEPS
    for key in ("cpus", "sched_fifo_max_priority", "memlock_limit_bytes", "timer_slack_ns",
                "cpu_governor", "isolated_cpus", "python"):
        assert key in report["os"]
    assert "bare loop at 2000 Hz" in out.stderr  # progress on stderr, JSON alone on stdout


def test_hardening_reports_every_step_and_restores_the_thread():
    policy, affinity = os.sched_getscheduler(0), os.sched_getaffinity(0)
    hardening = Hardening()
    steps = hardening.apply()
    try:
        assert [s.name for s in steps] == STEPS
        granted = {s.name: s.granted for s in steps}
        if granted["sched_fifo"]:
            assert os.sched_getscheduler(0) == os.SCHED_FIFO
        if granted["cpu_affinity"]:
            assert len(os.sched_getaffinity(0)) == 1
        assert granted["gc_freeze"] and not gc.isenabled()
        metadata = hardening.as_metadata()
        assert all(v.startswith(("granted: ", "refused: ")) for v in metadata.values())
    finally:
        hardening.restore()
    assert os.sched_getscheduler(0) == policy and os.sched_getaffinity(0) == affinity
    assert gc.isenabled()


REFUSED_CHILD = """
import json, os, resource
resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
resource.setrlimit(resource.RLIMIT_MEMLOCK, (65536, 65536))
from hil.core.realtime import Hardening  # imported first: root's files are not readable after
if os.geteuid() == 0:
    os.setgid(65534); os.setuid(65534)   # an unprivileged user: no CAP_SYS_NICE, CAP_IPC_LOCK
h = Hardening()
steps = h.apply()
h.restore()
print(json.dumps({s.name: [s.granted, s.detail] for s in steps}))
"""


def test_an_unprivileged_process_is_refused_and_told_why():
    out = subprocess.run([sys.executable, "-c", REFUSED_CHILD], capture_output=True, text=True,
                         timeout=60, cwd=REPO)
    assert out.returncode == 0, out.stderr
    steps = json.loads(out.stdout)
    assert steps["sched_fifo"][0] is False and "refused" in steps["sched_fifo"][1]
    assert steps["mlockall"][0] is False and "memlock limit 65536" in steps["mlockall"][1]
    assert steps["gc_freeze"][0] is True


@pytest.mark.realtime
def test_a_realtime_session_records_every_hardening_step_and_a_lockstep_one_none(tmp_path):
    from hil.core.clock import RealtimeClock, SimClock
    from hil.core.loop import FunctionTask
    from hil.core.recording.reader import read_session
    from hil.core.session import Session

    seen = {}

    def probe(_t):  # inside the loop: what the hardening did to the loop thread
        seen.setdefault("fifo", os.sched_getscheduler(0) == os.SCHED_FIFO)
        seen.setdefault("gc", gc.isenabled())

    for name, clock in (("rt", RealtimeClock()), ("sim", SimClock())):
        session = Session(str(tmp_path / f"{name}.mcap"), clock, 0.001, kind="test",
                          handle_signals=False)
        session.add_task(FunctionTask("probe", 1, write=probe))
        session.run(max_ticks=50)
        session.close()
        if name == "rt":
            assert gc.isenabled() and os.sched_getscheduler(0) != os.SCHED_FIFO  # restored
            inside = dict(seen)
            seen.clear()
    realtime = read_session(tmp_path / "rt.mcap")
    steps = realtime.metadata["realtime"]
    assert list(steps) == STEPS
    assert all(v.startswith(("granted: ", "refused: ")) for v in steps.values())
    assert inside["gc"] is False
    assert inside["fifo"] == steps["sched_fifo"].startswith("granted")
    event = next(m for _, m in realtime.topic("/events") if m["kind"] == "realtime.hardening")
    assert set(event["data"]["granted"]) | set(event["data"]["refused"]) == set(STEPS)
    lockstep = read_session(tmp_path / "sim.mcap")
    assert "realtime" not in lockstep.metadata and seen["gc"] is True


@pytest.mark.realtime
def test_hil_report_json_shows_the_loop_figures_and_what_was_granted(tmp_path, capsys):
    # the run and the report in this process (the hardening is undone when the run ends)
    path = tmp_path / "rt.mcap"
    run = hil_here(capsys, "servo", "run", "--controller", "pid", "--realtime", "--duration",
                   "0.3", "--out", path)
    assert run.returncode in (0, 2, 3), run.stderr  # a starved emulator: ended early, or disturbed
    report = json.loads(hil_here(capsys, "report", path, "--json").stdout)
    assert report["loop"]["servo"]["runs"] > 0
    assert set(report["loop"]["servo"]["lateness_us"]) >= {"p50", "p99", "max"}
    assert list(report["realtime"]) == STEPS


def test_a_worker_started_from_the_hardened_loop_thread_is_an_ordinary_thread():
    from concurrent.futures import ThreadPoolExecutor

    from hil.core.realtime import ordinary_thread

    def policy_and_cores():
        return os.sched_getscheduler(0), len(os.sched_getaffinity(0))

    hardening = Hardening()
    steps = {s.name: s.granted for s in hardening.apply()}
    try:
        with ThreadPoolExecutor(1) as plain, ThreadPoolExecutor(1,
                                                                initializer=ordinary_thread) as ok:
            inherited, reset = plain.submit(policy_and_cores).result(), \
                ok.submit(policy_and_cores).result()
    finally:
        hardening.restore()
    if steps["sched_fifo"]:
        assert inherited[0] == os.SCHED_FIFO  # what the initializer is for
    assert reset[0] == os.SCHED_OTHER and reset[1] == len(os.sched_getaffinity(0))


def test_hardening_keeps_helper_processes_and_the_writer_off_the_loops_core(tmp_path):
    from hil.core.realtime import forget_helper_process, register_helper_process
    from hil.core.recording.recorder import Recorder

    usable = sorted(os.sched_getaffinity(0))
    helper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    recorder = Recorder(tmp_path / "w.mcap")
    register_helper_process(helper.pid)
    hardening = Hardening()
    try:
        steps = {s.name: s for s in hardening.apply()}
        if len(usable) < 2:  # nothing to pin to: the step says so
            assert not steps["cpu_affinity"].granted
            return
        core = hardening.pinned_cpu
        assert steps["cpu_affinity"].granted and core is not None
        assert f"helper process(es) [{helper.pid}] kept off it" in steps["cpu_affinity"].detail
        assert core not in os.sched_getaffinity(helper.pid)
        recorder.keep_off_cpu(core)
        assert core not in os.sched_getaffinity(recorder.writer_pid)
    finally:
        hardening.restore()
        forget_helper_process(helper.pid)
        helper.kill()
        helper.wait()
        recorder.close()


def test_a_real_time_writer_process_yields_its_cpu_to_everything_else(tmp_path):
    """Real time (the producer never waits): the writer runs under SCHED_IDLE, so an emulator
    woken up on its core preempts it at once; where SCHED_IDLE is refused, at nice >= 10."""
    from hil.core.recording.recorder import Recorder

    recorder = Recorder(tmp_path / "rt.mcap", wait_when_full=False)
    lockstep = Recorder(tmp_path / "lockstep.mcap", wait_when_full=True)
    try:
        recorder.wait_ready()
        lockstep.wait_ready()
        policy = os.sched_getscheduler(recorder.writer_pid)
        assert policy == os.SCHED_IDLE or os.getpriority(os.PRIO_PROCESS,
                                                         recorder.writer_pid) >= 10
        assert os.sched_getscheduler(lockstep.writer_pid) == os.SCHED_OTHER
    finally:
        recorder.close()
        lockstep.close()


@pytest.mark.parametrize(("row", "fit", "because"), [
    ({"p50_us": 8.0, "p99_us": 40.0, "max_us": 180.0, "missed_pct": 0.0}, True,
     "lateness p99 40 us <= 100 us, max 180 us <= 500 us, no tick skipped"),
    ({"p50_us": 8.0, "p99_us": 140.0, "max_us": 180.0, "missed_pct": 0.0}, False,
     "lateness p99 140 us > 100 us"),
    ({"p50_us": 8.0, "p99_us": 40.0, "max_us": 2600.0, "missed_pct": 0.2}, False,
     "0.2 % of the ticks were skipped; lateness max 2600 us > 500 us (a whole period)"),
])
def test_the_verdict_names_what_a_2khz_loop_needs(row, fit, because):
    from hil.core.doctor import verdict

    assert verdict({"1000": row, "2000": row}) == {"fit_for_2khz": fit, "because": because}
    assert verdict({"1000": row})["fit_for_2khz"] is None
