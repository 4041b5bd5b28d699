"""The bench plant alone: motor inrush and coast-down, first-order loads, meter, levels,
sequence."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.bench.config import check_emulation, load_bench_config, parse_bench_config
from hil.bench.sequence import SequenceSchedule
from hil.core.config import deep_merge
from hil.emulators.bench.plant import COIL_LOG_LENGTH, BenchPlant, PlantSpec
from hil.errors import ConfigError


@pytest.fixture(scope="module")
def config():
    return load_bench_config()


def plant_spec(data: dict) -> PlantSpec:
    """The plant of a bench config given as TOML data, checked as an emulator checks it."""
    config = parse_bench_config(data)
    check_emulation(config)
    return config.plant


def run(plant: BenchPlant, seconds: float) -> list[dict[str, float]]:
    """Step ``seconds``; return the noise-free load powers after each step."""
    out = []
    for _ in range(round(seconds / plant.dt)):
        plant.step()
        out.append(plant.load_va())
    return out


@pytest.mark.parametrize(("motor", "steady_va"), [("P1", 110.0), ("P2", 80.0)])
def test_motor_inrush_then_steady_level(config, motor, steady_va):
    plant = BenchPlant(config.plant)
    plant.set_relay(motor, True)
    va = np.array([x[motor] for x in run(plant, 3.0)])
    assert va[0] == va.max()                              # the peak is the first sample
    assert 2.0 <= va[0] / steady_va <= 2.6                # inrush 2-2.6x the steady level
    assert np.all(np.diff(va) <= 1e-9)                    # falls while the rotor spins up
    settle_s = (np.argmax(np.abs(va - steady_va) < 0.05 * steady_va) + 1) * plant.dt
    assert 0.3 <= settle_s <= 0.6
    assert va[-1] == pytest.approx(steady_va, rel=1e-6)
    load = next(ld for ld in plant.loads if ld.name == motor)
    assert load.electrical(1.0)[1] < 0.55 < load.steady_pf  # poor power factor at standstill


def test_motor_switch_off_has_no_dip_and_coasts(config):
    plant = BenchPlant(config.plant)
    motor = next(ld for ld in plant.loads if ld.name == "P1")
    plant.set_relay("P1", True)
    cold_peak = max(x["P1"] for x in run(plant, 2.0))
    plant.set_relay("P1", False)
    after_off = [x["P1"] for x in run(plant, 0.3)]
    assert after_off == [0.0] * len(after_off)            # current stops at once, no negative dip
    assert 0.2 < motor.speed < 1.0 - motor.steady_slip   # the rotor is still turning, slower
    plant.set_relay("P1", True)
    warm_peak = max(x["P1"] for x in run(plant, 2.0))
    assert warm_peak < 0.9 * cold_peak                    # smaller inrush while coasting
    plant.set_relay("P1", False)
    run(plant, 5.0)
    assert motor.speed == 0.0                             # eventually at rest


@pytest.mark.parametrize(("load", "tau_s", "rated"), [("M1", 0.05, 230.0), ("M2", 0.4, 140.0)])
def test_first_order_machining_loads(config, load, tau_s, rated):
    plant = BenchPlant(config.plant)
    plant.set_relay(load, True)
    va = np.array([x[load] for x in run(plant, 10 * tau_s)])
    k_tau = round(tau_s / plant.dt) - 1
    assert va[k_tau] == pytest.approx(rated * (1 - math.exp(-1)), rel=1e-9)
    assert va[-1] == pytest.approx(rated, rel=1e-4)


@pytest.mark.parametrize(("consumer", "supplier"), [(False, False), (True, False),
                                                    (False, True), (True, True)])
def test_levels_follow_table_one_exactly(config, consumer, supplier):
    plant = BenchPlant(config.plant)
    table = {"q1": ("M1", "P1", -3.0, 5.0, 55.0), "q2": ("M2", "P2", -5.0, 7.0, 65.0)}
    for m, p, *_ in table.values():
        plant.set_relay(m, consumer)
        plant.set_relay(p, supplier)
    levels = []
    for _ in range(3):
        for _ in range(100):
            plant.step()
        levels.append(dict(plant.snapshot.levels))
    for name, (_m, _p, alpha, eta, q0) in table.items():
        per_second = alpha * consumer + eta * supplier
        for seconds, snap in enumerate(levels, start=1):
            assert snap[name] == pytest.approx(q0 + per_second * seconds, abs=1e-9)


def test_levels_leave_the_bounds_but_not_the_tank(config):
    plant = BenchPlant(config.plant)
    plant.set_relay("M1", True)                           # consume q1, never refill
    run(plant, 5.0)
    assert plant.snapshot.levels["q1"] == pytest.approx(40.0)  # below the 50 bound: not enforced
    run(plant, 20.0)
    assert plant.snapshot.levels["q1"] == 0.0             # an empty tank stays empty


def test_machining_sequence_period_28_s(config):
    sequence = SequenceSchedule(config.problem.sequence)
    assert sequence.period_s == 28.0 and sequence.relays == ["M1", "M2"]
    profile = sequence.profile(0.01)
    assert profile["M1"].sum() * 0.01 == pytest.approx(14.0)
    assert profile["M2"].sum() * 0.01 == pytest.approx(14.0)
    plant = BenchPlant(config.plant)
    total = []
    for k in range(2 * 2800):
        for name, on in sequence.states_at(round(k * 1e7)).items():
            plant.set_relay(name, on)
        plant.step()
        total.append(sum(plant.true_phase_power()[0]))
    total = np.array(total)
    first, second = total[100:2800], total[2900:5600]     # skip the first second of each cycle
    assert np.max(np.abs(first - second)) < 1e-5          # the power profile repeats every 28 s
    at = {t: total[round(t * 100)] for t in (2.0, 8.0, 13.5, 16.0, 19.0, 24.5, 27.0)}
    assert at[2.0] == pytest.approx(40.0) and at[19.0] == pytest.approx(40.0)   # idle
    assert at[8.0] == pytest.approx(270.0, rel=1e-3)                            # M1
    assert at[13.5] == pytest.approx(410.0, rel=1e-3)                           # peak
    assert at[24.5] == pytest.approx(410.0, rel=1e-3)                           # peak
    assert at[16.0] == pytest.approx(180.0, rel=1e-3)                           # M2
    assert at[27.0] == pytest.approx(180.0, rel=1e-3)


def test_meter_is_consistent_with_the_loads(config):
    plant = BenchPlant(config.plant)
    for name in ("M1", "M2", "P1"):
        plant.set_relay(name, True)
    run(plant, 3.0)
    errors, kwh = [], plant.snapshot.meter["import_kwh"]
    for _ in range(500):
        snap = plant.step()
        m = snap.meter
        va_true, w_true = plant.true_phase_power()
        errors.append(m["va_l2"] - va_true[1])
        assert m["va_l1"] == 0.0 and m["va_l3"] == 0.0    # nothing on L1, L3
        assert m["total_va"] == m["va_l1"] + m["va_l2"] + m["va_l3"]
        assert m["total_w"] == m["power_w_l1"] + m["power_w_l2"] + m["power_w_l3"]
        assert m["pf_l2"] == pytest.approx(w_true[1] / va_true[1])
        assert m["power_w_l2"] == pytest.approx(m["va_l2"] * m["pf_l2"])
        assert m["current_l2"] == pytest.approx(m["va_l2"] / m["voltage_l2"])
        assert m["va_l2"] ** 2 == pytest.approx(m["power_w_l2"] ** 2 + m["var_l2"] ** 2)
        assert abs(m["voltage_l1"] - 230.0) < 2.0 and m["frequency_hz"] == 50.0
        kwh += m["total_w"] * plant.dt / 3.6e6
        assert m["import_kwh"] == pytest.approx(kwh, rel=1e-9)
    assert va_true[1] == pytest.approx(40 + 230 + 140 + 110, rel=1e-3)  # additive per phase
    assert 1.0 < np.std(errors) < 2.0 and abs(np.mean(errors)) < 0.3    # sigma 1.5 VA


def test_noise_is_seeded(config):
    a, b, c = BenchPlant(config.plant), BenchPlant(config.plant), BenchPlant(config.plant, seed=99)
    for plant in (a, b, c):
        plant.set_relay("M1", True)
        run(plant, 0.5)
    assert a.snapshot.meter == b.snapshot.meter
    assert a.snapshot.meter["va_l2"] != c.snapshot.meter["va_l2"]


def test_disturbance_follows_its_schedule_only_when_enabled(config):
    off = BenchPlant(config.plant)
    assert [x["disturbance"] for x in run(off, 12.0)][-1] == 0.0
    enabled = {"plant": {"disturbance": {"enabled": True}}}
    on = BenchPlant(plant_spec(deep_merge(config.data, enabled)))
    va = np.array([x["disturbance"] for x in run(on, 70.0)])
    assert va[700] == 0.0                                   # 7 s: before the 8-20 s window
    assert va[1500] == pytest.approx(70.0)                  # 15 s: inside
    assert va[3000] < 1e-6                                  # 30 s: between windows
    assert va[4000] == pytest.approx(70.0)                  # 40 s: second window (36-44 s)
    assert va[5000] < 1e-6                                  # 50 s: after it
    assert va[6600] == pytest.approx(70.0)                  # 66 s = 56 + 10: repeated


@pytest.mark.parametrize(("override", "message"), [
    ({"relays": {"P2": {"coil": 2}}}, "relays P1 and P2 are both on coil 2"),
    ({"relays": {"P1": {"coil": "two"}}}, "key 'relays.P1.coil' must be an integer"),
    ({"plant": {"loads": {"P1": {"relay": "P9"}}}}, "names relay 'P9', not in [relays]"),
    ({"plant": {"loads": {"M2": {"pf": 1.5}}}}, "key 'plant.loads.M2.pf' must be <= 1, got 1.5"),
    ({"plant": {"base": {"phases": ["L4"]}}}, "key 'plant.base.phases' must list distinct"),
    ({"plant": {"loads": {"M1": {"model": "magic"}}}},
     "key 'plant.loads.M1.model' is neither first_order nor induction_motor nor a load model"),
    ({"relays": {"P1": {"coil": 9}}}, "relay module has 8 coils"),
    ({"plant": {"resources": {"q1": {"bounds": [150, 50]}}}}, "'plant.resources.q1.bounds'"),
])
def test_wrong_plant_config_is_one_clear_error(config, override, message):
    with pytest.raises(ConfigError) as err:
        BenchPlant(plant_spec(deep_merge(config.data, override)))
    assert message in str(err.value) and "\n" not in str(err.value)


def test_coil_log_keeps_only_the_latest_changes(config):
    plant = BenchPlant(config.plant)
    changes = COIL_LOG_LENGTH + 500
    for k in range(changes):
        plant.set_coils(0, [k % 2 == 0])
        plant.step()
    assert len(plant.coil_log) == COIL_LOG_LENGTH  # a day-long run keeps a bounded history
    assert plant.coil_log[-1] == (changes - 1, 0, (changes - 1) % 2 == 0)
    assert plant.coil_log[0] == (500, 0, True)
