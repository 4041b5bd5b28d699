"""The bench's configuration is read once, strictly: errors name the file and the key."""

from __future__ import annotations

import pytest

from hil.bench.config import (
    check_emulation,
    load_bench_config,
    load_configs,
    parse_bench_config,
)
from hil.bench.rig import attach_bench
from hil.cli.main import main
from hil.core.clock import SimClock
from hil.core.config import deep_merge
from hil.core.session import Session
from hil.errors import ConfigError

pytestmark = pytest.mark.timeout(60)

DEFAULT = load_bench_config()


def user_file(tmp_path, text: str) -> str:
    path = tmp_path / "mine.toml"
    path.write_text(text)
    return str(path)


def one_line_error(call, *args) -> str:
    with pytest.raises(ConfigError) as err:
        call(*args)
    message = str(err.value)
    assert "\n" not in message
    return message


@pytest.mark.parametrize(("text", "key", "why"), [
    ("[relays.P1]\ndwel_s = 2.0\n", "relays.P1.dwel_s", "unknown key"),
    ("[sampling]\nperiod_s = \"fast\"\n", "sampling.period_s", "must be a number"),
    ("[sampling]\nperiod_s = 0\n", "sampling.period_s", "must be >= 0.001 s, got 0 s"),
    ("[sampling]\nlevels_every = 0\n", "sampling.levels_every", "must be >= 1"),
    ("[relays.M1]\ndwell_s = -1.0\n", "relays.M1.dwell_s", "must be >= 0"),
    ("[relays.M1]\ncoil = -1\n", "relays.M1.coil", "a coil must be >= 0"),
    ("[levels.registers]\nq2 = 0x0001\n", "levels.registers.q2", "overlaps"),
    ("[bus]\ntimeout_s = 0.0\n", "bus.timeout_s", "must be > 0"),
    ("[plant.disturbance]\nperiod_s = -56.0\n", "plant.disturbance.period_s", "must be >= 0"),
    ("[[sequence.stages]]\nstart_s = 0.0\nend_s = 28.0\non = []\nof = []\n", "of",
     "unknown key"),
    ("[sampeling]\nperiod_s = 0.01\n", "sampeling", "unknown key"),
    # found by the fuzz campaign: taken, then numpy's ValueError building the plant
    ("[plant]\nseed = -1\n", "plant.seed", "must be >= 0, got -1"),
])
def test_a_bad_bench_file_is_one_error_naming_file_and_key(tmp_path, text, key, why):
    path = user_file(tmp_path, text)
    message = one_line_error(load_bench_config, path)
    assert message.startswith(f"{path}: ") and f"'{key}'" in message and why in message


def test_a_misspelt_eec_key_names_file_and_key(tmp_path):
    path = user_file(tmp_path, "[eec]\ndwell = 3.0\n")
    message = one_line_error(load_configs, path)
    assert message.startswith(f"{path}: unknown key 'eec.dwell'")
    assert "time_limit_s" in message  # says which keys there are


def test_eec_step_must_be_a_multiple_of_the_sampling_period(tmp_path):
    path = user_file(tmp_path, "[eec]\nstep_s = 0.015\n")
    message = one_line_error(load_configs, path)
    assert "'eec.step_s' = 0.015 is not a multiple of the sampling period 0.01 s" in message


def test_one_user_file_holds_tables_of_both_configs(tmp_path):
    path = user_file(tmp_path, "[relays.P1]\ndwell_s = 3.0\n[eec]\ngamma1 = 0.8\n")
    bench, eec = load_configs(path)
    assert bench.map.relays["P1"].dwell_s == 3.0 and bench.problem.dwell_s["P1"] == 3.0
    assert eec.eec.gamma1 == 0.8 and eec.eec.gamma2 == 0.1
    assert load_bench_config(path).map.relays["P1"].dwell_s == 3.0   # the bench alone too


def test_the_default_files_are_read_into_each_sides_dataclasses():
    bench, eec = load_configs()
    assert bench.source == "bench config" and eec.source == "eec config"
    assert bench.bus.url == "emulated" and bench.bus.watchdog_polls == 5
    assert bench.map.units == {"relays": 1, "meter": 2, "levels": 3}
    assert [(first, count) for first, count, _ in bench.map.meter_reads] == [(0, 76)]
    assert bench.problem.sequence.relays == ("M1", "M2")
    assert bench.problem.peripherals == ("P1", "P2")
    assert [load.name for load in bench.plant.loads] == ["M1", "M2", "P1", "P2"]
    assert bench.plant.relays == {"M1": 0, "M2": 1, "P1": 2, "P2": 3}
    assert bench.server.meter_space == (0x0000, 0x0050)
    assert eec.eec.hp_s == 28.0 and eec.eec.limit_va == 560.0
    assert set(eec.models) == {"machining", "P1", "P2"}


def test_dwell_override_reaches_controllers_safety_layer_and_record():
    config = DEFAULT.with_dwell(7.0)
    assert config.problem.dwell_s == {"P1": 7.0, "P2": 7.0}
    assert config.map.relays["P1"].dwell_s == 7.0 and config.map.relays["M1"].dwell_s == 1.0
    assert config.data["relays"]["P2"]["dwell_s"] == 7.0
    assert DEFAULT.problem.dwell_s == {"P1": 5.0, "P2": 5.0}   # the original is untouched


def test_what_only_the_emulator_needs_is_checked_when_emulating():
    # a real meter may have quantities the emulated one does not compute
    data = deep_merge(DEFAULT.data, {"meter": {"registers": {"thd_v_l1": 0x00EA}}})
    config = parse_bench_config(data)
    assert "thd_v_l1" in config.map.meter_quantities
    message = one_line_error(check_emulation, config)
    assert "key 'meter.registers.thd_v_l1' is not a quantity the meter provides" in message


def test_an_unknown_bench_url_scheme_lists_the_known_ones(tmp_path):
    session = Session(str(tmp_path / "x.mcap"), SimClock(), 0.01, kind="bench",
                      handle_signals=False)
    try:
        message = one_line_error(attach_bench, session, DEFAULT, "canopen://bus0")
    finally:
        session.close()
    assert "unknown scheme 'canopen'" in message
    assert "emulated, modbus-rtu, modbus-tcp" in message


@pytest.mark.parametrize("command", [
    ["bench", "run", "--controller", "bc", "--cycles", "1"],
    ["bench", "identify", "--relays", "P1", "--duration", "10"],
    ["emulate", "bench", "--tcp", "127.0.0.1:0"],
])
def test_the_cli_prints_one_error_line_for_a_bad_config_file(tmp_path, capsys, command):
    path = user_file(tmp_path, "[sampling]\nperiod_s = 0\n")
    assert main([*command, "--config", path]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == f"hil: error: {path}: key 'sampling.period_s' must be >= 0.001 s, got 0 s\n"
