"""Tests a user writes for their own controllers with hil's pytest fixtures.

``hil_bench`` and ``hil_drive`` start the emulators in their own processes for each test;
``pytest --hil-bench URL --hil-drive URL`` points the same tests at real hardware.
"""

from my_controllers import PdPosition, ThresholdRelays


def test_threshold_relays_keep_the_levels_in_range(hil_bench):
    kpis = hil_bench.run(ThresholdRelays, {"on_below": 75, "off_above": 130}, cycles=1)
    assert kpis["level_violations"] == 0
    assert kpis["dwell_violations"] == 0          # the safety layer held the 5 s dwell
    assert kpis["J2_VA"] < 700                    # the peak stays under the contracted power


def test_the_bench_driver_switches_a_relay_and_reads_power(hil_bench):
    bench = hil_bench.driver
    assert bench.set_relays({"P1": True}) == {"P1": "switched"}
    assert bench.relays()["P1"] is True
    power = bench.read_power()
    assert power is not None and power["total_va"] > 0


def test_pd_tracks_a_slow_sine_through_the_drive(hil_drive):
    kpis = hil_drive.run(PdPosition, {"kp": 300, "kd": 6}, reference="sine:amplitude=2,"
                         "frequency=1", duration_s=1.0, limits=["rms_error_deg<=0.5"])
    assert kpis["passed"], kpis["limits"]
    assert kpis["peak_current_mA"] <= 1000
