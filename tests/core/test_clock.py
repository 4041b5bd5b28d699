import time

import pytest

from hil.core.clock import RealtimeClock, SimClock, busy_share_max, spin_from


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


def test_a_wait_spins_its_margin_unless_the_cycle_would_be_busier_than_its_share():
    """The spin before a deadline keeps a cycle (from the last wake-up to the deadline) busy
    for at most the share: a tick of 100 us spins its 200 us margin, a tick of 300 us spins
    150 us (450 of 500 busy), a tick past 450 us sleeps all the way; a first wait and a share
    of 1.0 spin the margin."""
    woke, target, margin = 1_000_000, 1_500_000, 200_000
    assert spin_from(woke + 100_000, target, woke, margin, 0.9) == target - 200_000
    assert spin_from(woke + 300_000, target, woke, margin, 0.9) == target - 150_000
    assert spin_from(woke + 460_000, target, woke, margin, 0.9) == target
    assert spin_from(woke + 600_000, target, woke, margin, 0.9) == target  # already late
    assert spin_from(woke + 300_000, target, None, margin, 0.9) == target - margin
    assert spin_from(woke + 300_000, target, woke, margin, 1.0) == target - margin


def test_the_busy_share_stays_below_the_kernels_real_time_budget(tmp_path):
    """950 ms of real-time runtime a second (Linux's default) leaves a loop 90 % of each
    cycle; no budget (-1), no such file or nonsense: no cap. The clock takes it by default."""
    runtime, period = tmp_path / "runtime", tmp_path / "period"
    period.write_text("1000000\n")
    for text, share in (("950000\n", 0.90), ("500000\n", 0.45), ("-1\n", 1.0),
                        ("nonsense\n", 1.0)):
        runtime.write_text(text)
        assert busy_share_max(str(runtime), str(period)) == pytest.approx(share)
    assert busy_share_max(str(tmp_path / "none"), str(period)) == 1.0
    assert RealtimeClock().busy_share == busy_share_max()
    assert RealtimeClock(busy_share=0.5).busy_share == 0.5
