"""Bus time of classic CAN frames and the cycle-fit check."""

import pytest

from drivers.can_bus_time import (
    FrameLoad,
    cia402_cyclic_frames,
    cycle_budget,
    frame_bits,
)


def test_an_8_byte_frame_is_111_bits_nominal_and_135_with_worst_stuffing():
    assert frame_bits(8) == 111
    assert frame_bits(8, worst_case=True) == 135
    assert frame_bits(0) == 47 and frame_bits(0, worst_case=True) == 55
    assert frame_bits(8, extended=True) == 131
    assert frame_bits(8, extended=True, worst_case=True) == 160


def test_the_drive_cycle_at_1_mbit_fits_2_khz_but_not_4_khz():
    frames = cia402_cyclic_frames(500e-6)  # SYNC 0 + RPDO 4 + TPDO 6 + TPDO 6 bytes
    budget = cycle_budget(1_000_000, 500e-6, frames)
    assert budget.nominal_us == pytest.approx(47 + 79 + 95 + 95)
    assert budget.worst_us == pytest.approx(55 + 95 + 115 + 115)
    assert budget.fits and budget.warnings == ()
    fast = cycle_budget(1_000_000, 250e-6, cia402_cyclic_frames(250e-6))
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
    base = cycle_budget(500_000, 1e-3, cia402_cyclic_frames(1e-3))
    with_hb = cycle_budget(500_000, 1e-3, cia402_cyclic_frames(1e-3,
                                                               heartbeat_periods_s=[0.1]))
    assert with_hb.nominal_us - base.nominal_us == pytest.approx(55 * 2 * 0.01)


@pytest.mark.parametrize("bad", [
    lambda: frame_bits(9), lambda: FrameLoad("x", -1), lambda: cycle_budget(0, 1e-3, []),
    lambda: cycle_budget(1_000_000, 0.0, []),
])
def test_bad_inputs_raise(bad):
    with pytest.raises(ValueError):
        bad()
