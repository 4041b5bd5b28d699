"""``hil sweep`` on a local Ray (one per module, see conftest): grid and random sweeps, a
failing trial, --resume, a [sweep] table on the bench, determinism against a lone run, and
``hil servo figures`` as a preset sweep on Ray."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from hil.cli.main import main
from hil.controllers.servo.sim import figure_table

HERE = Path(__file__).resolve().parent
GAIN = f"{HERE / 'gain_controller.py'}:Gain"
TIMING = {"step_us", "wall_s", "realtime_factor", "mcap"}   # wall-clock figures, file name
SERVO = ["sweep", "servo", "--duration", "0.3", "--reference", "sine:amplitude=2,frequency=2"]

pytestmark = [pytest.mark.timeout(180), pytest.mark.slow]


def without_timing(kpis: dict) -> dict:
    return {k: v for k, v in kpis.items() if k not in TIMING}


def sweep_json(capsys, argv: list[str]) -> tuple[int, dict]:
    status = main([*argv, "--json"])
    captured = capsys.readouterr()
    return status, json.loads(captured.out)


def test_a_grid_sweep_runs_the_product_on_ray_and_matches_a_lone_run(local_ray, tmp_path,
                                                                     capsys):
    out = tmp_path / "grid"
    status, result = sweep_json(capsys, [*SERVO, "--controller", "pid", "--grid",
                                         "umax=200,800", "--grid", "ert=zoh,foh",
                                         "--out", str(out)])
    assert status == 0
    assert result["engine"] == "ray" and result["workers"] == 2 and result["wall_s"] > 0
    trials = result["trials"]
    assert sorted((t["params"]["umax"], t["params"]["ert"]) for t in trials) == [
        (200.0, "foh"), (200.0, "zoh"), (800.0, "foh"), (800.0, "zoh")]
    for trial in trials:
        assert trial["status"] == "ok"
        assert Path(trial["mcap"]) == out / f"umax-{trial['params']['umax']:g}_ert-"\
            f"{trial['params']['ert']}.mcap"
        assert Path(trial["mcap"]).stat().st_size > 1000
        assert trial["kpis"]["umax_mA"] == trial["params"]["umax"]
    # the current limit binds: a tighter one gives a smaller peak current
    peaks = {t["params"]["umax"]: t["kpis"]["peak_current_mA"] for t in trials}
    assert peaks[200.0] <= 200.0 < peaks[800.0]
    with (out / "results.csv").open() as f:
        table = list(csv.DictReader(f))
    assert [r["trial"] for r in table] == [t["name"] for t in trials]
    assert {"umax", "ert", "max_error_deg", "step_us.p99", "status"} <= set(table[0])
    assert (out / "sweep.png").stat().st_size > 10_000

    lone = trials[1]
    assert main(["servo", "run", *SERVO[2:], "--controller", "pid", "--umax",
                 f"{lone['params']['umax']:g}", "--ert", lone["params"]["ert"], "--json",
                 "--out", str(tmp_path / "lone.mcap")]) == 0
    alone = json.loads(capsys.readouterr().out)
    assert without_timing(lone["kpis"]) == without_timing(alone)


def test_a_random_sweep_of_a_plugin_parameter_is_seeded(local_ray, tmp_path, capsys):
    argv = [*SERVO, "--controller", GAIN, "--random", "3", "param.gain=50:400", "--seed",
            "7"]
    status, first = sweep_json(capsys, [*argv, "--out", str(tmp_path / "a")])
    assert status == 0
    gains = [t["params"]["param.gain"] for t in first["trials"]]
    assert len(set(gains)) == 3 and all(50 <= g <= 400 for g in gains)
    assert all(isinstance(g, int) for g in gains)   # integer bounds: integer samples
    assert len({t["kpis"]["rms_error_deg"] for t in first["trials"]}) == 3
    assert all(Path(t["mcap"]).name == f"gain-{t['params']['param.gain']}.mcap"
               for t in first["trials"])
    # the controller got its parameter: the same gain in a lone run gives the same KPIs
    trial = first["trials"][0]
    assert main(["servo", "run", *SERVO[2:], "--controller", GAIN, "--param",
                 f"gain={trial['params']['param.gain']}", "--json",
                 "--out", str(tmp_path / "lone.mcap")]) == 0
    alone = json.loads(capsys.readouterr().out)
    assert alone["rms_error_deg"] == trial["kpis"]["rms_error_deg"]
    # the same seed draws the same points
    status, second = sweep_json(capsys, [*argv, "--out", str(tmp_path / "b"), "--serial"])
    assert [t["params"]["param.gain"] for t in second["trials"]] == gains


def test_a_failing_trial_is_recorded_and_resume_reruns_only_what_is_missing(
        local_ray, tmp_path, capsys):
    out = tmp_path / "fail"
    assert main([*SERVO, "--controller", GAIN, "--grid", "param.gain=200,-1", "--out",
                 str(out), "--json"]) == 1
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    progress = captured.err.splitlines()   # not a terminal: one plain line per trial
    assert len(progress) == 2 and progress[-1].startswith("hil sweep: 2/2 trials, 1 failed")
    rows = {t["params"]["param.gain"]: t for t in result["trials"]}
    assert rows[200]["status"] == "ok" and rows[200]["kpis"]["ticks"] > 0
    assert rows[-1]["status"] == "failed" and "gain must be >= 0, got -1" in rows[-1]["error"]
    with (out / "results.csv").open() as f:
        table = {r["trial"]: r for r in csv.DictReader(f)}
    assert "gain must be >= 0" in table["gain--1"]["error"]

    done = out / "gain-200.json"
    before = done.stat().st_mtime_ns
    status, resumed = sweep_json(capsys, [*SERVO, "--controller", GAIN, "--grid",
                                          "param.gain=200,-1,300", "--out", str(out),
                                          "--resume"])
    assert status == 1   # the failing trial ran again, and failed again
    assert done.stat().st_mtime_ns == before
    assert [t["status"] for t in resumed["trials"]] == ["ok", "failed", "ok"]
    assert resumed["trials"][0]["kpis"] == rows[200]["kpis"]
    assert (out / "gain-300.mcap").is_file()


def test_a_bench_sweep_from_a_sweep_table_marks_the_pareto_front(local_ray, tmp_path, capsys):
    plan = tmp_path / "plan.toml"
    plan.write_text('[sweep]\nworkers = 2\n[sweep.grid]\ndwell = [5, 8]\n')
    out = tmp_path / "bench"
    status, result = sweep_json(capsys, ["sweep", "bench", "--controller", "bc", "--cycles",
                                         "1", "--sweep-config", str(plan), "--out", str(out)])
    assert status == 0 and result["workers"] == 2
    assert [t["params"] for t in result["trials"]] == [{"dwell": 5.0}, {"dwell": 8.0}]
    assert all(t["kpis"]["J1_VA"] > 0 and t["kpis"]["J2_VA"] > 0 for t in result["trials"])
    assert (out / "sweep.png").stat().st_size > 10_000


def test_servo_figures_as_a_sweep_on_ray_gives_the_table_of_the_serial_simulation(
        local_ray, capsys):
    assert main(["servo", "figures", "--max-ht", "1", "--workers", "2", "--json"]) == 0
    cases = json.loads(capsys.readouterr().out)["cases"]
    assert cases == json.loads(json.dumps(figure_table(horizons=[1])))
