"""A sweep ends where a run starts: ``hil sweep --out DIR`` writes ``DIR/best.toml``, the best
trial's parameters, and ``hil servo run --params DIR/best.toml`` runs that trial again (the
same KPIs, in lockstep), from the command line in a folder outside the repository."""

import json
import os
import subprocess
import sys

import pytest

pytestmark = [pytest.mark.slow]


def hil(cwd, *args):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd, capture_output=True,
                          text=True, env=env, timeout=600)


def test_the_best_trial_of_a_sweep_runs_again_from_best_toml(tmp_path):
    run = ["--controller", "pid", "--duration", "0.1", "--reference",
           "sine:amplitude=10,frequency=2"]
    swept = hil(tmp_path, "sweep", "servo", *run, "--grid", "param.ti_us=2000,4000",
                "--grid", "param.umax=300", "--grid", "settle=0,0.05", "--serial",
                "--out", "sw", "--json")
    assert swept.returncode == 0, swept.stderr
    result = json.loads(swept.stdout)
    trials = result["trials"]
    best = min(trials, key=lambda t: t["kpis"]["rms_error_deg"])
    assert result["best"] == {"trial": best["name"], "kpi": "rms_error_deg",
                              "value": best["kpis"]["rms_error_deg"],
                              "params": str(tmp_path / "sw" / "best.toml")}
    text = (tmp_path / "sw" / "best.toml").read_text()
    assert f"ti_us = {best['params']['param.ti_us']}\n" in text
    assert f"umax = {best['params']['param.umax']}\n" in text
    # a swept run option is no controller parameter: named as its flag in a comment
    settle = best["params"]["settle"]
    assert f"--params best.toml --settle {settle}" in text
    again = hil(tmp_path, "servo", "run", *run, "--settle", str(settle), "--params",
                "sw/best.toml", "--out", "again.mcap", "--json")
    assert again.returncode == 0, again.stderr
    kpis = json.loads(again.stdout)
    for key in ("rms_error_deg", "max_error_deg", "peak_current_mA", "ticks"):
        assert kpis[key] == best["kpis"][key], key
    others = [t["kpis"]["rms_error_deg"] for t in trials if t is not best]
    assert all(kpis["rms_error_deg"] < other for other in others)
