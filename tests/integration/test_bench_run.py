"""``hil bench run``: closed loop through the real Modbus TCP emulator (lockstep), constraint
satisfaction, the fallback on an infeasible start, the CLI contract and the report."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hil.bench.kpis import transitions
from hil.bench.run import BenchRunOptions, run_bench
from hil.cli.main import main
from hil.core.recording.reader import read_session
from hil.core.report import plot_session, summarize
from tests.pymodbus_bench import short_config

pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]

DESIGN_KEYS = {"controller", "cycles", "J1_VA", "J2_VA", "SEC_VA", "peak_VA", "energy_VAs",
               "overlap_s", "dwell_violations", "level_violations", "switches", "solve_ms",
               "mcap"}


def relay_series(data, name):
    relays = data.arrays("/bench/relays")
    t = (relays["log_time_ns"] - relays["log_time_ns"][0]) / 1e9
    return t, relays[name].astype(bool)


def test_eec_closed_loop_over_modbus_keeps_every_constraint(tmp_path):
    out = str(tmp_path / "eec.mcap")
    kpis = run_bench(BenchRunOptions(controller="eec", cycles=2, out=out,
                                     overrides={"time_limit_s": 0.2})).kpis
    assert kpis["dwell_violations"] == 0 and kpis["level_violations"] == 0
    assert kpis["fallbacks"] == 0
    data = read_session(out)
    assert not data.recovered
    # from the recording itself: 100 Hz samples, a plan per second, dwell and level bounds
    assert data.topic_counts["/bench/power"] == 5600
    assert data.topic_counts["/eec/plan"] == 56
    for name in ("P1", "P2"):
        t, on = relay_series(data, name)
        changes = t[transitions(on)]
        assert changes.size >= 2, f"{name} hardly switched: nothing was tested"
        assert np.min(np.diff(changes)) >= 5.0 - 1e-6
    levels = data.arrays("/bench/levels")
    assert levels["q1"].min() >= 50.0 and levels["q1"].max() <= 150.0
    assert levels["q2"].min() >= 60.0 and levels["q2"].max() <= 180.0
    power = data.arrays("/bench/power")["total_va"]
    assert kpis["J2_VA"] == pytest.approx(power.max(), abs=0.01)
    plans = data.arrays("/eec/plan")
    assert set(plans["status"]) <= {"optimal", "time_limit"}
    kinds = [m["kind"] for _, m in data.topic("/events")]
    assert kinds[-1] == "bench.safe"  # relays driven to their safe level at the end
    assert summarize(data)["kpis"]["J1_VA"] == kpis["J1_VA"]


def test_infeasible_start_falls_back_to_hysteresis_without_crashing(tmp_path):
    config = tmp_path / "low.toml"
    config.write_text("[plant.resources.q1]\nq0 = 30.0\n")  # far below q_min = 50
    out = str(tmp_path / "low.mcap")
    kpis = run_bench(BenchRunOptions(controller="eec", cycles=1, out=out,
                                     config_path=str(config),
                                     overrides={"time_limit_s": 0.2})).kpis
    assert kpis["fallbacks"] >= 1
    assert kpis["dwell_violations"] == 0
    data = read_session(out)
    fallbacks = [m for _, m in data.topic("/events") if m["kind"] == "eec.fallback"]
    assert len(fallbacks) == kpis["fallbacks"] and fallbacks[0]["level"] == "warning"
    t, p1 = relay_series(data, "P1")
    assert p1[t >= 0.5][0]  # the hysteresis rule refills q1 at once
    levels = data.arrays("/bench/levels")
    assert levels["q1"][-1] >= 50.0  # and the EEC took over again within the bounds
    kinds = [m["kind"] for _, m in data.topic("/events")]
    assert kinds[-1] == "bench.safe"


def test_cli_prints_the_design_json_keys(tmp_path, capsys):
    """A 4 s machining cycle: the keys and the plot, not the cycle, are what is looked at."""
    out = str(tmp_path / "bc.mcap")
    assert main(["bench", "run", "--controller", "bc", "--cycles", "1", "--json",
                 "--config", str(short_config(tmp_path)), "--out", out]) == 0
    kpis = json.loads(capsys.readouterr().out)
    assert set(kpis) >= DESIGN_KEYS
    assert kpis["controller"] == "bc"
    assert kpis["cycles"] == 1
    assert kpis["mcap"] == out
    assert set(kpis["solve_ms"]) == {"median", "p99", "max"}
    assert set(kpis["switches"]) == {"P1", "P2"}
    png = tmp_path / "bc.png"
    plot_session(read_session(out), str(png))
    assert png.stat().st_size > 20_000


def test_bad_model_file_is_one_error_line(tmp_path, capsys):
    config = tmp_path / "bad.toml"
    config.write_text('[models]\nP1 = "no/such/model.json"\n')
    assert main(["bench", "run", "--controller", "eec", "--cycles", "1", "--config",
                 str(config), "--out", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no/such/model.json" in err[0] and err[0].startswith("hil: error")
