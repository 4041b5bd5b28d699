"""Bridge side of the bench: config loading, the machining sequence player, the sampler topics."""

from __future__ import annotations

import os

import pytest

from hil.bench.config import load_bench_config, parse_bench_config
from hil.bench.rig import attach_bench
from hil.bench.sequence import SequenceSchedule
from hil.core.clock import SimClock
from hil.core.recording.reader import read_session
from hil.core.session import Session
from hil.errors import ConfigError

pytestmark = pytest.mark.timeout(60)

CONFIG = load_bench_config()


def test_user_config_is_laid_over_the_default(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text('[bus]\nurl = "modbus-rtu:///dev/ttyUSB0?baud=9600&parity=E"\n'
                    "[relays.P1]\ndwell_s = 10.0\n")
    config = load_bench_config(str(path)).data
    assert config["bus"]["url"].startswith("modbus-rtu:///dev/ttyUSB0")
    assert config["relays"]["P1"] == {"coil": 2, "safe": False, "dwell_s": 10.0}
    assert config["bus"]["timeout_s"] == CONFIG.data["bus"]["timeout_s"]
    with pytest.raises(ConfigError, match="config file not found"):
        load_bench_config(str(tmp_path / "missing.toml"))


def test_sequence_states_at_stage_boundaries():
    sequence = SequenceSchedule(CONFIG.problem.sequence)
    at = {t: sequence.states_at(round(t * 1e9)) for t in (0, 3.99, 4, 10, 14, 17, 21, 25, 28)}
    assert at[3.99] == {"M1": False, "M2": False} and at[4] == {"M1": True, "M2": False}
    assert at[10] == at[21] == {"M1": True, "M2": True}
    assert at[14] == at[25] == {"M1": False, "M2": True}
    assert at[17] == at[0] == at[28] == {"M1": False, "M2": False}


@pytest.mark.parametrize(("stages", "why"), [
    ([{"start_s": 0.0, "end_s": 10.0, "on": []}, {"start_s": 12.0, "end_s": 28.0, "on": []}],
     "expected start_s = 10"),
    ([{"start_s": 0.0, "end_s": 20.0, "on": ["M1"]}], "end at 20 s, not at period_s = 28 s"),
    ([{"start_s": 0.0, "end_s": 28.0, "on": ["M7"]}], "unknown relay(s) ['M7']"),
    ([{"start_s": 0.0, "end_s": 28.0}], "missing key 'on'"),
])
def test_bad_sequence_is_one_clear_error(stages, why):
    config = {**CONFIG.data, "sequence": {"period_s": 28.0, "stages": stages}}
    with pytest.raises(ConfigError) as err:
        parse_bench_config(config)
    assert why in str(err.value) and "\n" not in str(err.value)


@pytest.mark.slow
def test_player_and_sampler_in_lockstep(tmp_path):
    session = Session(str(tmp_path / "b.mcap"), SimClock(), 0.01, kind="bench",
                      config=CONFIG.data, handle_signals=False)
    rig = attach_bench(session, CONFIG, "emulated")
    session.run(duration_s=30.0)
    rig.close()
    session.close()
    relays = rig.emulator.plant.relays
    log = [(k, coil, on) for k, coil, on in rig.emulator.plant.coil_log]
    m1 = [(k, on) for k, coil, on in log if coil == relays["M1"]]
    m2 = [(k, on) for k, coil, on in log if coil == relays["M2"]]
    assert m1 == [(400, True), (1400, False), (2100, True), (2500, False)]
    assert m2 == [(1000, True), (1700, False), (2100, True), (2800, False)]  # 28 s: next cycle

    data = read_session(tmp_path / "b.mcap")
    assert data.topic_counts["/bench/power"] == 3000
    assert data.topic_counts["/bench/levels"] == 3000
    power = data.arrays("/bench/power")
    assert set(power) >= {"total_va", "va_l2", "import_kwh", "frequency_hz"}
    t = (power["log_time_ns"] - power["log_time_ns"][0]) / 1e9
    assert t[1] == pytest.approx(0.01) and t[-1] == pytest.approx(29.99)
    assert power["total_va"][round(12.0 * 100)] > 400     # a machining peak
    assert power["total_va"][round(2.0 * 100)] < 50       # idle
    levels = data.arrays("/bench/levels")
    # q1 = 55 - 3 * (seconds M1 has been on): M1 on 4-14 s and 21-25 s
    for second, expected in ((4, 55.0), (10, 37.0), (14, 25.0), (21, 25.0), (25, 13.0)):
        assert levels["q1"][second * 100] == pytest.approx(expected, abs=1e-4)
    relay_topic = data.arrays("/bench/relays")
    assert relay_topic["M1"][500] == 1 and relay_topic["M1"][1500] == 0
    assert relay_topic["link_up"].min() == 1
    assert rig.sampler.missed_power == 0 and rig.bench.stats.failed_polls == 0


def test_sampling_period_must_fit_the_loop(tmp_path):
    session = Session(str(tmp_path / "x.mcap"), SimClock(), 0.003, kind="bench",
                      handle_signals=False)
    with pytest.raises(ConfigError, match="not a multiple of the loop's base period"):
        attach_bench(session, CONFIG, "emulated")
    session.close()


@pytest.mark.slow
def test_a_realtime_emulated_bench_runs_in_a_process_of_its_own(tmp_path):
    from hil.core.clock import RealtimeClock
    from hil.emulator_process import EmulatorProcess

    config = load_bench_config()
    session = Session(str(tmp_path / "rt.mcap"), RealtimeClock(), 0.01, kind="bench",
                      handle_signals=False)
    rig = attach_bench(session, config, "emulated")
    try:
        assert isinstance(rig.emulator, EmulatorProcess)
        assert rig.emulator.pid != os.getpid() and rig.emulator.process.poll() is None
        session.run(duration_s=0.5)
        # every tick the loop ran polled the process's meter; how many ticks a loaded machine
        # lets it run is the realtime tests' matter (13 of 50 seen beside mypy and 3 workers)
        stats = session.loop.stats["bench_io"]
        assert rig.sampler.samples == stats.runs >= 1 and stats.runs + stats.missed >= 49
        assert rig.sampler.latest_power is not None
    finally:
        rig.close()
        session.close()
    assert rig.emulator.process.poll() is not None  # stopped with the rig
    events = [m for _, m in read_session(tmp_path / "rt.mcap").topic("/events")]
    assert any(e["kind"] == "emulator.process" for e in events)
