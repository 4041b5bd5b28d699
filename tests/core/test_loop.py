import time

import pytest

from hil.core.clock import RealtimeClock, SimClock
from hil.core.loop import FixedRateLoop, FunctionTask, Task


class Recording(Task):
    """Logs every phase with its time so order and schedule can be checked; what read took in
    goes through compute to write on the task itself."""

    def __init__(self, name, divisor, log):
        super().__init__(name, divisor)
        self.log = log
        self.safe_calls = 0
        self.value = None

    def read(self, t_ns):
        self.log.append((self.name, "read", t_ns))
        self.value = t_ns

    def compute(self, t_ns):
        self.log.append((self.name, "compute", t_ns))
        self.value += 1

    def write(self, t_ns):
        self.log.append((self.name, "write", self.value - 1))

    def record(self, t_ns):
        self.log.append((self.name, "record", t_ns))

    def safe_state(self):
        self.safe_calls += 1


def run_sim(ticks):
    log = []
    tasks = [Recording("sample", 1, log), Recording("control", 100, log), Recording("odd", 7, log)]
    loop = FixedRateLoop(SimClock(), 0.01, tasks, handle_signals=False)
    loop.run(max_ticks=ticks)
    return loop, log, tasks


def test_sim_loop_runs_each_task_on_its_divisor_exactly():
    loop, log, tasks = run_sim(1000)
    runs = {t.name: t for t in tasks}
    starts = {name: [t for n, phase, t in log if n == name and phase == "read"] for name in runs}
    assert len(starts["sample"]) == 1000
    assert len(starts["control"]) == 10
    assert len(starts["odd"]) == 143  # ticks 0, 7, ..., 994
    assert starts["control"] == [k * 1_000_000_000 for k in range(10)]
    assert starts["odd"] == [k * 70_000_000 for k in range(143)]
    assert loop.ticks == 1000 and loop.skipped_ticks == 0
    assert all(t.safe_calls == 1 for t in tasks)


def test_each_phase_runs_for_every_task_before_the_next_phase():
    _, log, _ = run_sim(1)
    assert [(n, p) for n, p, _ in log] == [
        ("sample", "read"), ("control", "read"), ("odd", "read"),
        ("sample", "compute"), ("control", "compute"), ("odd", "compute"),
        ("sample", "write"), ("control", "write"), ("odd", "write"),
        ("sample", "record"), ("control", "record"), ("odd", "record"),
    ]
    assert {t for _, _, t in log} == {0}  # write got what compute made of this tick's read


def test_a_task_takes_part_only_in_the_phases_it_defines_and_each_is_timed():
    class ReadOnly(Task):
        def read(self, t_ns):
            sum(range(100))

    calls = []
    tasks = [ReadOnly("sensor"), FunctionTask("ctl", 2, compute=calls.append),
             Recording("all", 1, [])]
    assert tasks[0].phases == ("read",) and tasks[1].phases == ("compute",)
    assert tasks[2].phases == ("read", "compute", "write", "record")
    loop = FixedRateLoop(SimClock(), 0.01, tasks, handle_signals=False)
    loop.run(max_ticks=10)
    assert calls == [k * 20_000_000 for k in range(5)]
    summary = loop.summary()
    assert set(summary["sensor"]) >= {"read_us", "tick_us"}
    assert "compute_us" not in summary["sensor"] and "read_us" not in summary["ctl"]
    assert summary["ctl"]["runs"] == 5 and summary["sensor"]["runs"] == 10
    for phase in ("read", "compute", "write", "record"):
        assert summary["all"][f"{phase}_us"]["max"] > 0
    # the tick is the sum of the phases: never less than the longest one
    assert summary["all"]["tick_us"]["max"] >= summary["all"]["read_us"]["max"]


def test_timing_records_hold_each_phase_under_its_own_name(tmp_path):
    from hil.core.recording.reader import read_session
    from hil.core.session import Session

    session = Session(str(tmp_path / "t.mcap"), SimClock(), 0.01, kind="test",
                      handle_signals=False)
    session.add_task(Recording("both", 1, []))
    session.add_task(FunctionTask("writer", 1, write=lambda t: None))
    session.run(max_ticks=150)
    session.close()
    messages = [m for _, m in read_session(str(tmp_path / "t.mcap")).topic("/loop/both/timing")]
    assert sum(m["runs"] for m in messages) == 150
    for phase in ("read", "compute", "write", "record"):
        assert sum(len(m[f"{phase}_us"]) for m in messages) == 150
    writer = [m for _, m in read_session(str(tmp_path / "t.mcap")).topic("/loop/writer/timing")]
    assert sum(len(m["write_us"]) for m in writer) == 150
    assert all(len(m["read_us"]) == 0 for m in writer)


def test_sim_loop_is_deterministic():
    loop_a, log_a, _ = run_sim(500)
    loop_b, log_b, _ = run_sim(500)
    assert log_a == log_b
    for name in ("sample", "control", "odd"):
        a, b = loop_a.stats[name].summary(), loop_b.stats[name].summary()
        for key in ("runs", "missed", "overruns", "measured_period_s", "lateness_us"):
            assert a[key] == b[key]
        assert a["lateness_us"]["max"] == 0
    assert loop_a.stats["control"].measured_period_s() == pytest.approx(1.0, abs=1e-12)


@pytest.mark.realtime
def test_realtime_overrun_is_skipped_and_counted_not_hidden():
    starts = []  # each run's tick number and start

    def read(t_ns):
        starts.append((loop.tick_number, t_ns))
        if len(starts) == 5:
            time.sleep(0.0105)  # a 10.5 ms stall in a 2 ms loop: ticks 5..9 cannot happen

    events = []
    loop = FixedRateLoop(
        RealtimeClock(), 0.002, [FunctionTask("fast", 1, read=read), FunctionTask("slow", 2)],
        on_event=lambda kind, msg, data: events.append((kind, data)), handle_signals=False,
    )
    loop.run(max_ticks=40)
    fast, slow = loop.stats["fast"], loop.stats["slow"]
    assert loop.skipped_ticks >= 4
    assert fast.runs + fast.missed == 40  # every scheduled run either ran or was counted missed
    assert fast.missed == loop.skipped_ticks
    assert slow.runs + slow.missed == 20
    assert fast.overruns >= 1  # the stalled step took longer than its period
    assert any(kind == "loop.overrun" for kind, _ in events)
    # the schedule stays on its absolute grid: each tick runs once, in order, never before its
    # slot's start, and none past the last scheduled one (a drifting loop would run late ticks
    # past 39); the stall's ticks are skipped, not run late. (Not asserted: that a run starts
    # within its slot. A preemption between the wait and the tick's clock reading, on a busy
    # machine, may put its start in the next slot.)
    ticks = [tick for tick, _ in starts]
    assert ticks == sorted(set(ticks))
    assert all(t - loop.start_ns >= tick * 2_000_000 for tick, t in starts)
    assert ticks[5] >= ticks[4] + 5  # 10.5 ms of a tick's 2 run into the 5th slot after it
    assert ticks[-1] <= 39 and len(ticks) + fast.missed == 40


def test_exception_in_task_calls_every_safe_state_and_propagates():
    log = []
    good = Recording("good", 1, log)

    def boom(t_ns):
        if t_ns >= 30_000_000:
            raise RuntimeError("controller exploded")

    component = Recording("driver", 1, [])
    loop = FixedRateLoop(SimClock(), 0.01, [good, FunctionTask("bad", 1, compute=boom)],
                         handle_signals=False)
    loop.add_component(component)
    with pytest.raises(RuntimeError, match="exploded"):
        loop.run(max_ticks=100)
    assert good.safe_calls == 1 and component.safe_calls == 1
    assert loop.stop_reason.startswith("error: RuntimeError")


def test_failing_safe_state_hook_does_not_stop_the_others():
    class Broken(Task):
        def safe_state(self):
            raise OSError("bus gone")

    ok = Recording("ok", 1, [])
    events = []
    loop = FixedRateLoop(SimClock(), 0.01, [ok, Broken("broken")], handle_signals=False,
                         on_event=lambda kind, msg, data: events.append(kind))
    loop.run(max_ticks=3)
    assert ok.safe_calls == 1
    assert "safe_state.failed" in events


def test_stop_request_from_a_task_ends_the_loop_at_the_tick_boundary():
    loop = FixedRateLoop(SimClock(), 0.01, [], handle_signals=False)
    loop.add_task(FunctionTask("watch", 1, read=lambda t: t >= 50_000_000 and loop.stop("done")))
    loop.run(max_ticks=1000)
    assert loop.ticks == 6 and loop.stop_reason == "done"


@pytest.mark.parametrize("bad", [0, -1, 1.5])
def test_bad_divisor_is_refused(bad):
    with pytest.raises(ValueError, match="divisor"):
        Task("x", bad)


def test_duplicate_task_names_are_refused():
    loop = FixedRateLoop(SimClock(), 0.01, [Task("a")], handle_signals=False)
    with pytest.raises(ValueError, match="duplicate"):
        loop.add_task(Task("a"))


class LateClock(SimClock):
    """A real-time clock that wakes tick ``late_tick`` up a nanosecond short of a period late,
    and lets 2 ns pass before the tick starts: its start falls in the next slot."""

    mode = "realtime"

    def __init__(self, period_ns: int, late_tick: int) -> None:
        super().__init__()
        self.period_ns, self.late_tick, self.waits = period_ns, late_tick, 0

    def wait_until(self, deadline_ns: int) -> int:
        late = self.period_ns - 1 if self.waits == self.late_tick else 0
        self.waits += 1
        self._now_ns = max(self._now_ns, deadline_ns + late)
        return late

    def time_ns(self) -> int:
        self._now_ns += 1
        return self._now_ns


def test_a_tick_that_starts_in_the_next_slot_keeps_its_own_number():
    period_ns = 1_000_000
    numbers: list[tuple[int, int]] = []
    loop: FixedRateLoop

    def note(t_ns: int) -> None:
        numbers.append((loop.tick_number, (t_ns - loop.start_ns) // period_ns))

    loop = FixedRateLoop(LateClock(period_ns, late_tick=3), period_ns / 1e9,
                         [FunctionTask("noted", 1, compute=note)], handle_signals=False)
    loop.run(max_ticks=6)
    assert [number for number, _ in numbers] == [0, 1, 2, 3, 4, 5]  # no skip, no repeat
    assert numbers[3] == (3, 4)  # it started in slot 4's time, and is tick 3
