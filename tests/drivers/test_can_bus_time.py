"""Bus time of classic CAN frames and the cycle-fit check."""

import pytest

from hil.drivers.can_bus_time import (
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
    assert fast.warnings == ("the cyclic CAN traffic needs 380 us per cycle at 1000000 bit/s "
                             "(worst case: every frame with all the stuff bits it can take): "
                             "more than the 250 us period",)


def test_one_figure_the_worst_case_a_period_only_the_best_case_fits_does_not_fit():
    frames = [FrameLoad("SYNC", 0), FrameLoad("PDO", 8, per_cycle=3)]  # 380 / 460 bits
    budget = cycle_budget(1_000_000, 400e-6, frames)
    assert not budget.fits
    assert "460 us" in budget.warnings[0] and "380" not in budget.warnings[0]
    assert budget.summary()["load_worst"] == pytest.approx(460 / 400, abs=1e-3)
    assert cycle_budget(1_000_000, 460e-6, frames).fits  # the worst case, no more margin


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
    assert three.bus_time_us == three.budget.worst_us  # the one figure
    problem = three.problem()
    assert problem.startswith("3 axes need 1032 us of bus time per cycle at 1000000 bit/s "
                              "(worst case: every frame with all the stuff bits it can take): "
                              "more than the 500 us period; ways out: ")
    assert 1033 < three.min_period_us <= 1034
    assert "master.cycle_period_us >= 1034 (968 Hz or slower)" in problem
    assert "3 buses, 1 axis per bus" in problem
    assert "fewer mapped objects" not in problem  # no leaner layout was given
    lean = [AxisTraffic(f"a{i}", tpdo_bytes=(8,)) for i in range(3)]
    with_lean = plan_bus(1_000_000, 500e-6, axes, 0.05, lean=lean, lean_how="one TPDO")
    assert with_lean.lean_us is not None and with_lean.lean_us < three.bus_time_us
    assert f"fewer mapped objects: one TPDO: {with_lean.lean_us:.0f} us, not enough alone" in \
        with_lean.problem()
    summary = with_lean.summary()
    assert summary["bus_time_us"] == round(three.bus_time_us, 1) and not summary["fits"]
    assert "nominal_us" not in summary and "worst_us" not in summary  # one figure
    # at the shortest period they fit (within rounding), just below it they do not
    assert plan_bus(1_000_000, three.min_period_us * 1.001e-6, axes, 0.05).fits
    assert not plan_bus(1_000_000, three.min_period_us * 0.999e-6, axes, 0.05).fits
    # fewer mapped bytes: one 8-byte TPDO per axis brings three axes under 1 kHz
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
