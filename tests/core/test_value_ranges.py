"""Values the code cannot honour are refused before anything is opened, each with one line
naming the flag or key (exit 2): durations too long for a run's timestamps or too short to
run a tick, horizons and dwells whose allocations would exhaust the machine, sampling periods
that divide by zero, configs nested too deeply to parse."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from hil.cli.main import main

pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
SERVO = ["servo", "run", "--controller", "pid"]
BENCH = ["bench", "run", "--controller", "bc"]


def refused(capsys, *argv):
    code = main(list(argv))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith("hil: error: "), err
    return err[0]


@pytest.mark.parametrize(("argv", "named"), [
    ([*SERVO, "--duration", "1e12"], "--duration 1e+12 s is longer than a run can be"),
    ([*SERVO, "--duration", "1e-9"], "--duration 1e-09 s is shorter than one tick"),
    ([*SERVO, "--hp", "100000000"], "--hp 1e+08 is above 1000"),
    ([*SERVO, "--ht", "5000"], "--ht 5000 is above 1000"),
    ([*BENCH, "--hp", "100000000"], "--hp 1e+08 is above 600"),
    ([*BENCH, "--dwell", "1e12"], "--dwell: key 'relays.P1.dwell_s' must be <= 3600 s"),
    ([*BENCH, "--cycles", "100000"], "--cycles 100000: 2.8e+06 s is longer"),
])
def test_out_of_range_flags_are_one_line(tmp_path, capsys, argv, named):
    line = refused(capsys, *argv, "--out", str(tmp_path / "x.mcap"))
    assert named in line
    assert not (tmp_path / "x.mcap").exists()


@pytest.mark.parametrize(("toml", "named"), [
    ("[sampling]\nperiod_s = 1e-12\n", "sampling.period_s"),
    ("[relays.M2]\ndwell_s = 4.5\n", "relays.M2.dwell_s = 4.5 s is not shorter than the "
                                     "shortest time the sequence holds M2 on or off (4 s)"),
    ("[relays.P1]\ndwell_s = 1e9\n", "relays.P1.dwell_s"),
    ("[eec]\nhp_s = 1e8\n", "eec.hp_s"),
    ("a = " + "[" * 100000 + "]" * 100000 + "\n", "nested too deeply to be a config"),
])
def test_out_of_range_config_values_are_one_line(tmp_path, capsys, toml, named):
    config = tmp_path / "bench.toml"
    config.write_text(toml)
    line = refused(capsys, "bench", "run", "--controller", "bc", "--config", str(config),
                   "--out", str(tmp_path / "x.mcap"))
    assert named in line and str(config) in line


def test_a_deeply_nested_config_is_one_line_from_the_command_line(tmp_path):
    config = tmp_path / "deep.toml"
    config.write_text("a = " + "[" * 100000 + "]" * 100000 + "\n")
    done = subprocess.run([sys.executable, "-m", "hil", *SERVO, "--config", str(config)],
                          capture_output=True, text=True, timeout=60,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)), check=False)
    assert done.returncode == 2
    assert done.stderr.strip() == f"hil: error: {config}: nested too deeply to be a config " \
                                  "(at most 16 levels)"
