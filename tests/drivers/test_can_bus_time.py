"""Bus time of classic CAN frames and the cycle-fit check."""

import pytest

from drivers.can_bus_time import (
    AxisTraffic,
    FrameLoad,
    bus_frames,
    cycle_budget,
    frame_bits,
    plan_bus,
)


def one_drive(period_s, heartbeats=()):
    """SYNC + RPDO 4 + TPDO 6 + TPDO 6 bytes (+ heartbeats): one drive's cycle."""
    frames = bus_frames(period_s, [AxisTraffic("x", heartbeat_period_s=0)])
    return frames + [FrameLoad("hb", 1, per_cycle=period_s / p) for p in heartbeats]


def test_an_8_byte_frame_is_111_bits_nominal_and_135_with_worst_stuffing():
    assert frame_bits(8) == 111
    assert frame_bits(8, worst_case=True) == 135
    assert frame_bits(0) == 47 and frame_bits(0, worst_case=True) == 55
    assert frame_bits(8, extended=True) == 131
    assert frame_bits(8, extended=True, worst_case=True) == 160


def test_the_drive_cycle_at_1_mbit_fits_2_khz_but_not_4_khz():
    budget = cycle_budget(1_000_000, 500e-6, one_drive(500e-6))
    assert budget.nominal_us == pytest.approx(47 + 79 + 95 + 95)
    assert budget.worst_us == pytest.approx(55 + 95 + 115 + 115)
    assert budget.fits and budget.warnings == ()
    fast = cycle_budget(1_000_000, 250e-6, one_drive(250e-6))
    assert not fast.fits
    assert "cannot fit" in fast.warnings[0] and "250 us" in fast.warnings[0]


def test_a_period_that_fits_only_without_stuffing_is_flagged():
    frames = [FrameLoad("SYNC", 0), FrameLoad("PDO", 8, per_cycle=3)]  # 380 / 460 bits
    budget = cycle_budget(1_000_000, 400e-6, frames)
    assert not budget.fits
    assert "only if the data stuffs little" in budget.warnings[0]
    assert budget.summary()["load_worst"] == pytest.approx(460 / 400, abs=1e-3)


def test_the_design_estimate_of_four_8_byte_frames_is_about_400_us():
    frames = [FrameLoad("any", 8, per_cycle=4)]
    assert cycle_budget(1_000_000, 1e-3, frames).nominal_us == pytest.approx(444)


def test_heartbeats_add_their_share_per_cycle():
    base = cycle_budget(500_000, 1e-3, one_drive(1e-3))
    with_hb = cycle_budget(500_000, 1e-3, one_drive(1e-3, heartbeats=[0.1]))
    assert with_hb.nominal_us - base.nominal_us == pytest.approx(55 * 2 * 0.01)


def test_one_axis_fits_2_khz_at_1_mbit_and_three_do_not_with_where_the_limit_is():
    axes = [AxisTraffic(f"a{i}") for i in range(3)]
    one = plan_bus(1_000_000, 500e-6, axes[:1], master_heartbeat_s=0.05)
    assert one.fits and one.problem() is None and one.max_axes == 1
    three = plan_bus(1_000_000, 500e-6, axes, master_heartbeat_s=0.05)
    assert not three.fits and three.max_axes == 1
    # SYNC once, then 3 x (RPDO 4 + TPDO 6 + TPDO 6), worst-case stuffing, plus heartbeats
    assert three.budget.worst_us == pytest.approx(55 + 3 * (95 + 115 + 115) + 65 * (
        3 * 500e-6 / 0.1 + 500e-6 / 0.05))
    problem = three.problem()
    assert "3 axes need 1032 us" in problem and "500 us period" in problem
    assert "even without bit stuffing" in problem
    assert "a period of at least 1033 us (968 Hz)" in problem and "3 buses" in problem
    assert "fewer mapped objects (the TPDOs carry 36 bytes" in problem
    # at the shortest period they fit (within rounding), just below it they do not
    assert plan_bus(1_000_000, three.min_period_us * 1.001e-6, axes, 0.05).fits
    assert not plan_bus(1_000_000, three.min_period_us * 0.999e-6, axes, 0.05).fits
    # fewer mapped bytes: one 8-byte TPDO per axis brings three axes under 1 kHz
    lean = [AxisTraffic(f"a{i}", tpdo_bytes=(8,)) for i in range(3)]
    assert not plan_bus(1_000_000, 1e-3, axes, 0.05).fits
    assert plan_bus(1_000_000, 1e-3, lean, 0.05).fits


def test_a_plan_with_no_room_even_for_one_axis_says_another_bus_does_not_help():
    problem = plan_bus(125_000, 500e-6, [AxisTraffic("a"), AxisTraffic("b")]).problem()
    assert problem is not None and "another bus does not help" in problem


@pytest.mark.parametrize("bad", [
    lambda: plan_bus(1_000_000, 1e-3, []),
    lambda: frame_bits(9), lambda: FrameLoad("x", -1), lambda: cycle_budget(0, 1e-3, []),
    lambda: cycle_budget(1_000_000, 0.0, []),
])
def test_bad_inputs_raise(bad):
    with pytest.raises(ValueError):
        bad()
