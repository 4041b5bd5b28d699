"""``hil sweep`` without Ray: the one-line errors, a real drive swept one trial after another
(--serial), the error when Ray is not installed, and the parts (space, names, Pareto front)."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import pytest

from hil import api
from hil.cli.main import main
from hil.cli.servo import add_run_arguments
from hil.sweep.plot import pareto_front
from hil.sweep.space import Space, expand
from tests.cli import hil_here

pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]


def error_of(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    return err


@pytest.mark.parametrize(("argv", "message"), [
    (["sweep", "bench", "--controller", "bc", "--bench", "modbus-tcp://127.0.0.1:5020",
      "--grid", "dwell=5,8"],
     "hil: error: --bench modbus-tcp://127.0.0.1:5020 is not emulated: a real device cannot "
     "run trials in parallel; add --serial to run them one after another"),
    (["sweep", "servo", "--controller", "pid", "--grid",
      "drive=emulated,socketcand://127.0.0.1:29536"],
     "hil: error: --drive socketcand://127.0.0.1:29536 is not emulated: a real device cannot "
     "run trials in parallel; add --serial to run them one after another"),
    (["sweep", "servo", "--controller", "pid", "--grid", "speed=1,2"],
     "hil: error: --grid 'speed=1,2': unknown key 'speed'"),
    (["sweep", "servo", "--controller", "pid", "--grid", "ht=4,zero"],
     "hil: error: --grid 'ht=4,zero': ht=zero: expected a positive integer, got 'zero'"),
    (["sweep", "servo", "--controller", "pid", "--grid", "ert=foh,hold"],
     "hil: error: --grid 'ert=foh,hold': ert=hold: expected one of foh, zoh"),
    (["sweep", "servo", "--controller", "pid", "--random", "3", "umax=900:100"],
     "hil: error: --random 'umax=900:100': lo must not exceed hi"),
    (["sweep", "servo", "--controller", "pid", "--grid", "umax=500,900", "--address",
      "10.0.0.1:6379"],
     "hil: error: --address 10.0.0.1:6379: expected auto (the cluster this machine is part "
     "of) or ray://HOST:PORT"),
    (["sweep", "servo", "--controller", "pid"],
     "hil: error: nothing to sweep: give --grid, --random or a [sweep] table"),
    # every trial is planned before Ray starts: a controller that cannot load, a limit on
    # no KPI, a value out of range are usage errors, not 2 failed trials of 2
    (["sweep", "servo", "--controller", "nothere.py:Pd", "--grid", "umax=500,900"],
     "hil: error: trial umax-500: 'nothere.py:Pd': no such file 'nothere.py'"),
    (["sweep", "servo", "--controller", "pid", "--grid", "umax=500,900", "--limit",
      "rms_err<=1"], "hil: error: trial umax-500: limit 'rms_err<=1': no KPI or signal"),
    (["sweep", "servo", "--controller", "pid", "--grid", "duration=1,1e12"],
     "hil: error: trial duration-1e+12: --duration 1e+12 s is longer than a run can be"),
])
def test_bad_sweeps_are_refused_in_one_line(capsys, argv, message):
    assert error_of(capsys, argv).startswith(message)


def test_a_sweep_table_with_an_unknown_key_is_refused(capsys, tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text("[sweep]\nworker = 2\n")
    assert error_of(capsys, ["sweep", "servo", "--controller", "pid", "--sweep-config",
                             str(plan)]) == (
        f"hil: error: {plan}: unknown key 'sweep.worker' (did you mean 'sweep.workers'? known "
        "here: address, grid, random, seed, workers)")


def test_a_real_drive_is_swept_one_trial_after_another_with_serial(capsys, tmp_path):
    with api.start_drive_emulator() as emulator:   # its own process, socketcand on loopback
        status = main(["sweep", "servo", "--controller", "pid", "--drive", emulator.url,
                       "--duration", "0.3", "--grid", "umax=500,900", "--serial",
                       "--out", str(tmp_path), "--json"])
    result = json.loads(capsys.readouterr().out)
    assert status == 0
    assert result["engine"] == "serial" and result["workers"] == 1
    assert [t["status"] for t in result["trials"]] == ["ok", "ok"]
    assert all(t["kpis"]["drive"].startswith("socketcand://") and t["kpis"]["ticks"] > 100
               for t in result["trials"])


def test_without_ray_the_sweep_names_the_extra_to_install(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)   # `import ray` now raises ImportError
    proc = hil_here(capsys, "sweep", "servo", "--controller", "pid", "--grid", "umax=500,900",
                    "--out", tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip() == ("hil: error: sweeps run on Ray, which is not installed: "
                                   "pip install 'hil[sweep]'")


def test_a_local_ray_that_cannot_start_is_one_line_naming_why(tmp_path):
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("")
    code = ("import sys\n"
            "from hil.cli.main import main\n"
            "sys.exit(main(['sweep', 'servo', '--controller', 'pid', '--duration', '0.05',"
            f" '--grid', 'umax=500,900', '--out', {str(tmp_path / 'out')!r}]))")
    # Ray's temporary folder is a file: the real Ray fails to start
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "RAY_TMPDIR": str(not_a_folder)})
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.startswith("hil:")]
    assert lines == [f"hil: error: the local Ray for the sweep did not start: [Errno 20] Not a "
                     f"directory: '{not_a_folder}/ray' (--serial runs the trials without Ray)"]
    assert "Traceback" not in proc.stderr


def servo_space() -> Space:
    parser = argparse.ArgumentParser()
    add_run_arguments(parser)
    return Space(parser)


def test_the_grid_is_the_cartesian_product_named_by_its_parameters():
    space = servo_space()
    grid = dict([space.grid_entry("ht=2,4"), space.grid_entry("ert=zoh,foh"),
                 space.grid_entry("reference=sine:amplitude=1,frequency=2;hold:position=0")])
    trials = expand(grid)
    assert len(trials) == 8
    assert trials[0].params == {"ht": 2, "ert": "zoh",
                                "reference": "sine:amplitude=1,frequency=2"}
    assert trials[0].name == "ht-2_ert-zoh_reference-sine_amplitude=1_frequency=2"
    assert len({t.name for t in trials}) == 8


def test_random_points_are_seeded_and_combined_with_the_grid():
    space = servo_space()
    ranges = [space.range_entry("umax=100:2000"), space.range_entry("param.kp=0.5:2.5")]
    samples = space.sample(ranges, 4, seed=3)
    assert samples == space.sample(ranges, 4, seed=3) != space.sample(ranges, 4, seed=4)
    assert all(100 <= s["umax"] <= 2000 and 0.5 <= s["param.kp"] <= 2.5 for s in samples)
    trials = expand(dict([space.grid_entry("ert=zoh,foh")]), samples)
    assert len(trials) == 8 and trials[0].params["ert"] == "zoh"


def test_names_that_clash_after_cleaning_get_a_suffix():
    trials = expand({"reference": ["a b", "a_b"]})
    assert [t.name for t in trials] == ["reference-a_b", "reference-a_b-2"]


def test_the_pareto_front_keeps_the_points_nothing_beats_on_both():
    points = [(3.0, 1.0), (1.0, 3.0), (2.0, 2.0), (2.5, 2.5), (1.0, 4.0)]
    assert pareto_front(points) == [1, 2, 0]


def test_results_csv_has_one_status_the_trials_and_the_runs_as_run_status(capsys, tmp_path):
    """The trial's status (ok / violated) and its run's (completed / violated) are two
    columns: a KPI named ``status`` no longer overwrites the trial's."""
    import csv

    import pandas

    out = tmp_path / "sweep"
    done = hil_here(capsys, "sweep", "servo", "--controller", "pid", "--duration", "0.2",
                    "--grid", "reference=sine:amplitude=1,frequency=1;"
                    "sine:amplitude=2,frequency=1", "--limit", "max_error_deg<=0.35",
                    "--serial", "--out", out, "--json")
    assert done.returncode == 1, done.stderr  # one trial violated its limit
    trials = json.loads(done.stdout)["trials"]
    assert [(t["status"], t["run_status"]) for t in trials] == [("ok", "completed"),
                                                                ("violated", "violated")]
    with (out / "results.csv").open(newline="") as f:
        header = next(csv.reader(f))
        f.seek(0)
        rows = list(csv.DictReader(f))
    assert header.count("status") == 1 and header.count("run_status") == 1
    assert header[:3] == ["trial", "status", "run_status"]
    assert [(r["status"], r["run_status"]) for r in rows] == [("ok", "completed"),
                                                              ("violated", "violated")]
    table = pandas.read_csv(out / "results.csv")
    assert list(table["status"]) == ["ok", "violated"]
    assert list(table["run_status"]) == ["completed", "violated"]
    assert not any(str(column).startswith("status.") for column in table.columns)
