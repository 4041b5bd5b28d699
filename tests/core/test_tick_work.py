"""No tick does a period's worth of the loop process's bookkeeping.

What the loop process does for its records besides the tick's own phases - samples binned into
the run's histograms, values handed to the recorder - is counted tick by tick in a lockstep
servo session (counted, not timed: the count is the same on any machine). A job left for every
N ticks (a timing window binned at once, a window's samples handed over as lists) costs one
tick the work of N: at 2 kHz, the once-a-second timing record cost a skipped tick every
second. The check is first shown to find such a job in a loop that has one.

Counted: each sample a histogram bins (``add``: 1, ``add_many``: its length) and each value a
topic is handed to pickle for the writer (a message 1, a list or buffer in it its length; a
row of a column topic, :class:`ColumnTopic`, its length). Counting a buffer as one copy
missed the timing record's five buffers of a second's samples, pickled at once: 100-300 us
on the loop's core in a real-time run, a late tick after each whole second.
"""

from __future__ import annotations

from array import array

import pytest

from hil.core.clock import SimClock
from hil.core.loop import FixedRateLoop, FunctionTask
from hil.core.recording.recorder import ColumnTopic, Topic
from hil.core.session import Session
from hil.core.stats import TimingHistogram
from hil.servo.run import ServoRunOptions, run_servo

pytestmark = pytest.mark.timeout(120)

#: a tick's own bookkeeping, with room: the servo tick's samples (lateness, four phases, step,
#: the controller's compute time), its three messages, the MPC's prediction as two lists
#: (8 and 50 values) and its timing row: some 75 values
TICK_BOUND = 100


class TickWork:
    """Spies on the histograms and the topics: the values each tick hands them."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.per_tick: dict[int, int] = {}
        self.tick: int | None = None  # None: outside the ticks (set-up, safe stop)
        add, add_many, log = TimingHistogram.add, TimingHistogram.add_many, Topic.log
        add_row, log_columns = ColumnTopic.add, ColumnTopic.log
        boundary, safe = FixedRateLoop._run_ticks, FixedRateLoop.safe_state_all
        work = self

        def counted_add(histogram: TimingHistogram, value: float) -> None:
            work.count(1)
            add(histogram, value)

        def counted_add_many(histogram: TimingHistogram, samples) -> None:
            work.count(len(samples))
            add_many(histogram, samples)

        def counted_log(topic: Topic, t_ns: int, message) -> bool:
            values = message.values() if isinstance(message, dict) else message
            work.count(1 + sum(len(v) for v in values if isinstance(v, list | array)))
            return log(topic, t_ns, message)

        def counted_row(columns: ColumnTopic, row: tuple[float, ...]) -> None:
            work.count(len(row))
            add_row(columns, row)

        def counted_columns(columns: ColumnTopic, t_ns: int, fields, names) -> bool:
            work.count(1 + sum(len(v) for v in fields.values() if isinstance(v, list | array)))
            return log_columns(columns, t_ns, fields, names)

        def run_ticks(loop: FixedRateLoop, limit) -> None:
            def at(n: int) -> None:
                work.tick = n
                if previous is not None:
                    previous(n)
            previous, loop.at_boundary = loop.at_boundary, at
            boundary(loop, limit)

        def safe_state_all(loop: FixedRateLoop) -> list[str]:
            work.tick = None  # the safe stop's records are not a tick's
            return safe(loop)

        monkeypatch.setattr(TimingHistogram, "add", counted_add)
        monkeypatch.setattr(TimingHistogram, "add_many", counted_add_many)
        monkeypatch.setattr(Topic, "log", counted_log)
        monkeypatch.setattr(ColumnTopic, "add", counted_row)
        monkeypatch.setattr(ColumnTopic, "log", counted_columns)
        monkeypatch.setattr(FixedRateLoop, "_run_ticks", run_ticks)
        monkeypatch.setattr(FixedRateLoop, "safe_state_all", safe_state_all)

    def count(self, values: int) -> None:
        if self.tick is not None:
            self.per_tick[self.tick] = self.per_tick.get(self.tick, 0) + values

    def heaviest(self) -> tuple[int, int]:
        """(values, tick) of the tick that did the most."""
        return max((values, tick) for tick, values in self.per_tick.items())


def test_the_check_finds_a_job_left_for_every_n_ticks(monkeypatch, tmp_path):
    # a task that keeps a window of samples and, every 2000 ticks, bins and records it at
    # once (lists): the way the loop's timing windows were published
    work = TickWork(monkeypatch)
    session = Session(str(tmp_path / "n.mcap"), SimClock(), 1e-3, kind="test")
    topic = session.topic("/windowed", {"type": "object", "properties": {
        "samples": {"type": "array", "items": {"type": "number"}}}})
    histogram, window = TimingHistogram(), []

    def record(t_ns: int) -> None:
        window.append(t_ns / 1e6)
        if len(window) == 2000:
            histogram.add_many(window)
            topic.log(t_ns, {"samples": list(window)})
            window.clear()

    session.add_task(FunctionTask("windowed", record=record))
    session.run(max_ticks=5000)
    session.close()
    values, tick = work.heaviest()
    assert values > TICK_BOUND and tick % 2000 == 1999, (values, tick)


@pytest.mark.slow
def test_no_tick_of_a_servo_session_does_a_windows_work(monkeypatch, tmp_path):
    work = TickWork(monkeypatch)
    out = tmp_path / "mpc.mcap"
    result = run_servo(ServoRunOptions("mpc", duration_s=3.0, out=str(out)))
    assert result.kpis["ticks"] == 6000 and len(work.per_tick) == 6000
    values, tick = work.heaviest()
    # three timing windows of 2000 ticks were recorded, each with 2000 samples of each phase
    assert values <= TICK_BOUND, f"tick {tick} did {values} values' worth of bookkeeping"
    assert sorted(set(work.per_tick.values()))[0] > 0  # every tick is counted


def test_the_timing_record_is_built_in_the_writer_a_row_a_tick(monkeypatch, tmp_path):
    """Each run of a task hands its lateness and phase times over as one row; the window's
    record hands over no samples, only its other fields: the writer makes the columns."""
    from hil.core.recording.reader import read_session

    rows: list[tuple[float, ...]] = []
    records: list[tuple[dict, tuple[str, ...]]] = []
    add, log = ColumnTopic.add, ColumnTopic.log

    def kept_row(columns: ColumnTopic, row: tuple[float, ...]) -> None:
        rows.append(row)
        add(columns, row)

    def kept(columns: ColumnTopic, t_ns: int, fields, names) -> bool:
        records.append((fields, names))
        return log(columns, t_ns, fields, names)

    monkeypatch.setattr(ColumnTopic, "add", kept_row)
    monkeypatch.setattr(ColumnTopic, "log", kept)
    out = str(tmp_path / "t.mcap")
    session = Session(out, SimClock(), 1e-3, kind="test")
    session.add_task(FunctionTask("tick", read=lambda t: None))
    session.run(max_ticks=2500)
    session.close()
    assert len(rows) == 2500 and {len(row) for row in rows} == {2}  # lateness, read
    assert [names for _, names in records] == [("lateness_us", "read_us")] * 3
    assert [fields["runs"] for fields, _ in records] == [1000, 1000, 500]
    assert all(len(v) == 0 for fields, _ in records for v in fields.values()
               if isinstance(v, array))  # only the phases the task has no part in
    recorded = [m for _, m in read_session(out).topic("/loop/tick/timing")]
    assert [len(m["read_us"]) for m in recorded] == [1000, 1000, 500]
    assert [len(m["lateness_us"]) for m in recorded] == [1000, 1000, 500]
    assert [len(m["compute_us"]) for m in recorded] == [0, 0, 0]  # not a phase of the task
    assert [m["runs"] for m in recorded] == [1000, 1000, 500]
    read_us = [v for m in recorded for v in m["read_us"]]
    assert read_us == pytest.approx([row[1] for row in rows], rel=1e-6, abs=1e-3)  # float32
