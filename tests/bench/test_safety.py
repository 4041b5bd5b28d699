"""The bench run's safety limits and bad readings, from outside: a power ceiling and the
levels' physical range stop the run with every relay at its safe level (exit 2, one line);
a meter serving NaN for a while is a fault (counted, recorded, kept out of the KPIs, exit 3,
valid JSON). The bench here is pymodbus's own server (tests/pymodbus_bench.py) or hil's
emulator; the run is the ``hil`` command in a process of its own."""

import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil import api
from hil.bench.config import load_bench_config
from hil.core.recording.reader import read_session
from hil.errors import ConfigError, SafetyStopError
from tests.pymodbus_bench import PymodbusBench, session_events, short_config

pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
CONFIG = load_bench_config()
# a 4 s machining cycle, so that a real-time run is short
def hil(*args, timeout=60):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "hil", *args], capture_output=True, text=True,
                          env=env, timeout=timeout, check=False)
    return done, time.monotonic() - start


def test_power_above_the_ceiling_stops_the_run_with_the_relays_safe(tmp_path):
    config = short_config(tmp_path)
    out = tmp_path / "over.mcap"
    with PymodbusBench(CONFIG, total_va=1500.0) as bench:
        done, _ = hil("bench", "run", "--controller", "bc", "--bench", bench.url, "--cycles",
                      "1", "--config", str(config), "--out", str(out))
        assert done.returncode == 2, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and "safety stop at t=" in lines[0]
        assert re.search(r"total_va 150\d\.\d VA above 1200 VA for more than 500 ms", lines[0])
        assert not any(bench.relays().values())       # every relay at its safe level
    stop = [e for e in session_events(out) if e["kind"] == "safety.stop"]
    assert len(stop) == 1
    # stopped once the window (50 samples of 10 ms) was over, everything before it recorded
    power = read_session(str(out)).topic("/bench/power")
    assert 50 <= len(power) <= 100


def test_a_level_outside_its_physical_range_stops_the_run(tmp_path):
    with pytest.raises(SafetyStopError, match=r"level q1 = 55.00 outside its physical range "
                                              r"\[56, 250\]"):
        api.run_bench("bc", safety={"level_min": 56}, out=str(tmp_path / "low.mcap"))
    stop = [e for e in session_events(tmp_path / "low.mcap") if e["kind"] == "safety.stop"]
    assert len(stop) == 1


def test_the_defaults_leave_the_built_in_controllers_alone(tmp_path):
    kpis = api.run_bench("bc", out=str(tmp_path / "bc.mcap"))
    assert kpis["stop_reason"] == "completed" and kpis["peak_VA"] < 1200


@pytest.mark.parametrize(("key", "value", "why"), [
    ("level_max", -1, "must be above level_min"),
    ("max_total_va", 0, "max_total_va"),
    ("max_total_va_ms", "x", "max_total_va_ms"),
    ("colour", 1, "colour"),
])
def test_a_wrong_safety_override_is_one_line_before_the_run(tmp_path, key, value, why):
    with pytest.raises(ConfigError, match=why):
        api.run_bench("bc", safety={key: value}, out=str(tmp_path / "x.mcap"))
    assert not (tmp_path / "x.mcap").exists()


def test_non_finite_readings_are_faults_out_of_the_kpis(tmp_path):
    config = short_config(tmp_path)
    out = tmp_path / "nan.mcap"

    def garbage(read):  # reads 101..150: NaN, then inf; the rest are good
        return math.nan if 100 < read <= 130 else math.inf if 130 < read <= 150 else None

    with PymodbusBench(CONFIG, total_va=300.0, meter_override=garbage) as bench:
        done, _ = hil("bench", "run", "--controller", "bc", "--bench", bench.url, "--cycles",
                      "1", "--config", str(config), "--out", str(out), "--json")
    assert done.returncode == 3, done.stderr
    kpis = json.loads(done.stdout, parse_constant=lambda name: pytest.fail(f"{name} in JSON"))
    assert kpis["faults"]["bad_readings"] == 50 and kpis["disturbed"] is True
    assert 299 < kpis["peak_VA"] < 302 and math.isfinite(kpis["J1_VA"])
    assert "RuntimeWarning" not in done.stderr
    assert [line for line in done.stderr.splitlines() if line] == [
        line for line in done.stderr.splitlines() if line.startswith("hil: run disturbed")]
    bad = [e for e in session_events(out) if e["kind"] == "meter.bad_reading"]
    assert len(bad) == 1 and "total_va = nan" in bad[0]["message"]
    totals = [m["total_va"] for _, m in read_session(str(out)).topic("/bench/power")]
    assert all(math.isfinite(v) for v in totals)
    # every good answer recorded: all the meter gave but the probe at open and the 50 bad ones,
    # less what the run did not take (late, retried); on the wall clock, a loaded machine
    # polls fewer times than 400, so the count is the meter's, not the sequence's
    faults = kpis["faults"]
    good = bench.meter_reads - 1 - 50
    assert good - faults["failed_polls"] - faults["retries"] <= len(totals) <= good
    assert len(totals) > 100  # the good answers after the bad ones too (reads 151 on)
