import time

from hil.core.clock import RealtimeClock, SimClock


def test_simclock_jumps_to_deadlines_without_sleeping():
    clock = SimClock()
    assert clock.start() == 0
    t0 = time.perf_counter()
    seen = []
    for k in range(1, 100_001):
        clock.wait_until(k * 1_000_000)
        seen.append(clock.time_ns())
    assert seen == [k * 1_000_000 for k in range(1, 100_001)]  # exactly on every deadline
    assert time.perf_counter() - t0 < 5.0  # nowhere near 100 s of virtual time: no sleeping
    clock.wait_until(5)
    assert clock.time_ns() == 100_000 * 1_000_000  # a past deadline never moves time backwards


def test_realtime_clock_wakes_at_or_after_deadline_and_reports_lateness():
    clock = RealtimeClock(spin_margin_ns=300_000)
    start = clock.start()
    for k in range(1, 21):
        deadline = start + k * 2_000_000
        lateness = clock.wait_until(deadline)
        assert lateness >= 0
        assert clock.time_ns() >= deadline
    # a deadline in the past returns at once with its lateness
    assert clock.wait_until(clock.time_ns() - 5_000_000) >= 5_000_000
