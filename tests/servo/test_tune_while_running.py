"""Parameters changed while a servo run runs (hil/core/tuning.py): a request from another
thread, through the run's tuner (``tuner_started``), is checked, applied at a tick boundary
and recorded; before that tick the run is the run without the change, after it the change
shows in the recorded error and command. Refused requests leave the run as it was."""

import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from hil import api
from hil.core.recording.reader import read_session
from hil.core.tuning import TunableSpec, Tuner
from tests.cli import hil_here
from tests.docs import block

REFERENCE = "sine:amplitude=10,frequency=2"
PERIOD_S = 500e-6


class Client:
    """Asks for changes from its own thread: ``asks`` submitted (checked and queued, a rebuild
    done) before the loop's first tick, so each lands exactly at its tick; then ``later``
    ones asked while the loop runs; then it waits for every answer."""

    def __init__(self, asks, later=()):
        self.asks = asks              # (name, value, at_tick)
        self.later = later            # (name, value)
        self.results = []
        self._thread = None

    def __call__(self, tuner):
        queued = threading.Event()

        def run():
            pending = [tuner.submit(name, value, "test-client", at_tick=at_tick)
                       for name, value, at_tick in self.asks]
            queued.set()
            later = [tuner.submit(name, value, "test-client") for name, value in self.later]
            self.results.extend(tuner.wait(p, 600.0) for p in pending + later)

        self._thread = threading.Thread(target=run)
        self._thread.start()
        assert queued.wait(600.0)

    def join(self):
        self._thread.join()
        return self.results


def run(tmp_path, name, controller, client=None, seconds=0.3):
    out = tmp_path / f"{name}.mcap"
    kpis = api.run_servo(controller, reference=REFERENCE, duration_s=seconds, out=str(out),
                         quiet=True, tuner_started=client)
    return kpis, read_session(out)


def ticks_of(session):
    commands = session.arrays("/drive/command")
    return np.round(commands["t_s"] / PERIOD_S).astype(int), commands


@pytest.fixture(scope="module")
def pid_runs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pid")
    _, plain = run(folder, "plain", "pid")
    client = Client([("controller.kp", 500.0, None),                  # out of range
                     ("safety.following_error_deg", 90.0, None),      # a loosening
                     ("controller.kv", "fast", None),                 # not a number
                     ("controller.kp", 0.6, 200),
                     ("safety.current_limit_mA", 150.0, 400)])
    kpis, tuned = run(folder, "tuned", "pid", client)
    return plain, tuned, client.join(), kpis


def test_a_pid_gain_set_while_running_takes_effect_at_its_tick(pid_runs):
    plain, tuned, results, _ = pid_runs
    kp = results[3]
    assert (kp.accepted, kp.value, kp.tick, kp.reason) == (True, 0.6, 200, "")
    ticks, before = ticks_of(plain)
    tuned_ticks, after = ticks_of(tuned)
    assert np.array_equal(ticks, tuned_ticks)
    head = ticks < 200
    for field in ("error_deg", "command_mA"):
        assert np.array_equal(before[field][head], after[field][head])
        assert not np.allclose(before[field][~head], after[field][~head])
    # a sixth of the position gain: the tracking error grows
    late = ticks >= 300
    rms = [float(np.sqrt(np.mean(run["error_deg"][late] ** 2))) for run in (before, after)]
    assert rms[1] > 1.1 * rms[0], rms


def test_refused_requests_say_why_and_leave_the_run_as_it_was(pid_runs):
    plain, tuned, results, _ = pid_runs
    out_of_range, loosened, not_a_number = results[:3]
    assert not out_of_range.accepted and out_of_range.tick is None
    assert out_of_range.value == pytest.approx(3.6111)
    assert "outside its range [0, 100] rpm/deg" in out_of_range.reason
    assert not loosened.accepted and loosened.value == 45.0
    assert "may only be lowered" in loosened.reason and "45 deg" in loosened.reason
    assert not not_a_number.accepted and "takes a number [A/rpm]" in not_a_number.reason
    ticks, before = ticks_of(plain)
    _, after = ticks_of(tuned)
    assert np.array_equal(before["error_deg"][ticks < 200], after["error_deg"][ticks < 200])


def test_a_tightened_current_limit_clamps_the_drive_from_its_tick(pid_runs):
    _, tuned, results, kpis = pid_runs
    limit = results[4]
    assert (limit.accepted, limit.tick) == (True, 400)
    ticks, _ = ticks_of(tuned)
    feedback = tuned.arrays("/drive/feedback")
    current = np.abs(feedback["command_mA"])
    # feedback of tick k reports the command of tick k - 1
    assert current[ticks >= 402].max() <= 150.5
    assert current[ticks < 400].max() > 150.5
    assert kpis["current_limit_mA"] == 150.0


def test_every_change_and_refusal_is_recorded(pid_runs):
    _, tuned, _, _ = pid_runs
    events = [m for _, m in tuned.topic("/events") if m["kind"].startswith("param.")]
    changed = [e["data"] for e in events if e["kind"] == "param.changed"]
    refused = [e["data"] for e in events if e["kind"] == "param.refused"]
    assert [(c["parameter"], c["old"], c["new"], c["client"], c["tick"]) for c in changed] == [
        ("controller.kp", 3.6111, 0.6, "test-client", 200),
        ("safety.current_limit_mA", 1000.0, 150.0, "test-client", 400)]
    assert [r["parameter"] for r in refused] == [
        "controller.kp", "safety.following_error_deg", "controller.kv"]
    params = [m for _, m in tuned.topic("/params")]
    assert [(p["parameter"], p["new"], p["unit"], p["tick"]) for p in params] == [
        ("controller.kp", 0.6, "rpm/deg", 200), ("safety.current_limit_mA", 150.0, "mA", 400)]
    stamps = [t for t, _ in tuned.topic("/params")]
    start = tuned.topic("/drive/command")[0][0]
    assert [round((t - start) / 1e9 / PERIOD_S) for t in stamps] == [200, 400]


def test_an_mpc_horizon_is_rebuilt_and_swapped_at_its_tick(tmp_path):
    _, plain = run(tmp_path, "plain", "mpc", seconds=0.2)
    # the second is prepared once the first is in place: H_u may not exceed the new H_p
    client = Client([("controller.hp", 20, 150)], later=[("controller.hu", 30)])
    kpis, tuned = run(tmp_path, "tuned", "mpc", client, seconds=0.2)
    hp, hu = client.join()
    assert (hp.accepted, hp.tick, hp.value) == (True, 150, 20)
    assert not hu.accepted and "must not exceed H_p (20)" in hu.reason
    assert kpis["hp"] == 20 and kpis["ticks"] == 400 and kpis["deadline_misses"] == 0
    assert sum(kpis["solver_paths"].values()) == 400
    ticks, before = ticks_of(plain)
    _, after = ticks_of(tuned)
    head = ticks < 150
    assert np.array_equal(before["command_mA"][head], after["command_mA"][head])
    assert not np.allclose(before["command_mA"][~head], after["command_mA"][~head])
    predicted = [len(m["y_deg"]) for _, m in tuned.topic("/mpc/prediction")]
    assert predicted[:150] == [50] * 150 and set(predicted[150:]) == {20}


def test_the_tuner_checks_types_and_refuses_after_the_run():
    applied = []
    tuner = Tuner()
    tuner.add(TunableSpec("controller.n", 8, "ticks", 1, 50, 1, False, None, ""),
              applied.append)
    tuner.add(TunableSpec("controller.on", False, "", None, None, None, False, None, ""),
              applied.append)
    assert "whole number [ticks]" in tuner.request("controller.n", 2.5, "t", 1.0).reason
    assert "true or false" in tuner.request("controller.on", 1, "t", 1.0).reason
    pending = tuner.submit("controller.n", "12", "t")
    tuner.tick(7)
    assert tuner.wait(pending, 1.0).tick == 7 and applied == [12]
    assert tuner.specs()[0].value == 12
    tuner.close()
    late = tuner.request("controller.n", 9, "t", 1.0)
    assert (late.accepted, late.value, late.reason) == (False, 12, "the run has ended")


def test_report_and_export_show_the_changes(pid_runs, capsys):
    _, tuned, _, _ = pid_runs
    report = hil_here(capsys, "report", tuned.path)
    assert report.returncode == 0, report.stderr
    lines = report.stdout.splitlines()
    first = lines.index("params   changed while running")
    assert lines[first + 1].startswith("  controller.kp = 500 refused (test-client): "
                                       "controller.kp = 500 rpm/deg is outside its range")
    assert "  controller.kp: 3.6111 -> 0.6 at tick 200 (test-client)" in lines
    assert "  safety.current_limit_mA: 1000 -> 150 at tick 400 (test-client)" in lines
    exported = hil_here(capsys, "export", tuned.path, "--topic", "/params")
    assert exported.returncode == 0, exported.stderr
    assert exported.stdout.splitlines() == [
        "t_s,log_time_ns,parameter,old,new,unit,client,tick",
        "0.1,100000000,controller.kp,3.6111,0.6,rpm/deg,test-client,200",
        "0.2,200000000,safety.current_limit_mA,1000.0,150.0,mA,test-client,400"]


@pytest.mark.slow  # a process of its own: make test runs it, make check does not
def test_the_guides_example_tunes_a_run_from_outside_the_repository(tmp_path):
    code = block("guides/tuning.md", "python", "tuner_started=tune")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                          text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith("[('controller.kp', 3.6111, 'rpm/deg'), ")
    assert lines[1].startswith("TuneResult(name='safety.following_error_deg', accepted=False, "
                               "value=45.0, reason='safety.following_error_deg is a safety "
                               "limit: while running it may only be lowered")
    assert lines[2] == "TuneResult(name='controller.kp', accepted=True, value=2.5, reason='', " \
                       "tick=200)"


def test_rebuilds_run_in_turn_off_the_caller_and_the_end_of_the_run_refuses_the_rest():
    swapped = []
    tuner = Tuner()
    tuner.add(TunableSpec("controller.h", 8, "ticks", 1, 50, 1, True, None, ""),
              swapped.append, prepare=lambda value: lambda: swapped.append(value))
    first = tuner.submit("controller.h", 10, "t")     # returns at once: the worker rebuilds
    second = tuner.submit("controller.h", 12, "t")    # rebuilt once the first is in place
    n = 0
    while not first.done.is_set():                   # the loop's tick boundaries
        tuner.tick(n)
        n += 1
    assert tuner.wait(first, 60.0).tick is not None and swapped == [10]
    tuner.close()
    late = tuner.wait(second, 60.0)
    assert not late.accepted and late.value == 10 and "the run ended" in late.reason
    assert swapped == [10] and tuner.specs()[0].value == 10


@pytest.mark.parametrize("lockstep", [True, False])
def test_in_lockstep_a_change_asked_for_at_a_tick_waits_there_for_its_rebuild(lockstep):
    """A slow rebuild (a busy machine, a big horizon) asked for at tick 3, done only once the
    loop is there: in lockstep the loop waits at tick 3 until it is built, so the session is
    the same however long it takes on the wall clock; in real time the loop goes on, and it
    lands at a later tick."""
    release = threading.Event()

    def prepare(value):
        release.wait(60.0)
        return lambda: None

    tuner = Tuner(lockstep=lockstep)
    tuner.add(TunableSpec("controller.h", 8, "ticks", 1, 50, 1, True, None, ""),
              lambda value: None, prepare=prepare)
    asked = tuner.submit("controller.h", 10, "t", at_tick=3)

    def release_at_tick_3():  # the rebuild ends only once the loop has reached tick 3
        while tuner.now < 3:
            time.sleep(0.001)
        release.set()

    threading.Thread(target=release_at_tick_3).start()
    n = 0
    while not asked.done.is_set():
        tuner.tick(n)
        n += 1
    result = tuner.wait(asked, 60.0)
    assert result.accepted
    assert result.tick == 3 if lockstep else result.tick > 3
    tuner.close()


@pytest.mark.parametrize("controller, params", [
    ("pid", {"kp": 3.0, "kv": 0.05, "ti_us": 4000.0, "umax": 800.0, "notch_hz": 500.0,
             "notch_q": 2.0}),
    ("mpc", {"ht": 6, "hu": 6, "hp": 40, "umax": 900.0, "q": 2e5, "r": 2.0}),
])
def test_a_tunable_is_a_param_of_the_same_name_and_unit(tmp_path, controller, params):
    """A value tuned while running goes back into --param as it is: each built-in's tunable
    ``controller.NAME`` starts at the ``--param NAME`` given."""
    seen: dict[str, float] = {}

    def note(tuner):
        seen.update({s.name: s.value for s in tuner.specs() if s.name.startswith("controller.")})

    api.run_servo(controller, params, reference=REFERENCE, duration_s=0.005,
                  out=str(tmp_path / "s.mcap"), quiet=True, tuner_started=note)
    assert {name: seen[f"controller.{name}"] for name in params} == pytest.approx(params)
