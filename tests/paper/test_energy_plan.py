"""The energy paper's runs as planned (``hil.paper.energy_runs``), before anything runs: the
paper's conditions as configured, one run per distinct set of flags, every point of the J1
sensitivity study backed by a run, and the variant configs each a valid bench config that
differs from the paper's in its one condition."""

from __future__ import annotations

from hil.bench.config import load_bench_config
from hil.core.config import load_toml
from hil.paper.energy_runs import (
    KNOBS,
    bc_cycle_s,
    knob_values,
    paper_config,
    plan_runs,
    shift_change,
)

PAPER = load_bench_config(str(paper_config()))


def test_the_paper_config_holds_the_papers_conditions():
    problem, eec = PAPER.problem, load_toml(paper_config())[0]["eec"]
    assert problem.sequence.period_s == 28.0 and PAPER.sampling.period_s == 0.01
    assert {(r.alpha, r.eta, r.q_min, r.q_max, r.q0) for r in problem.resources} == {
        (-3.0, 5.0, 50.0, 150.0, 55.0), (-5.0, 7.0, 60.0, 180.0, 65.0)}   # Table I
    assert problem.dwell_s == {"P1": 5.0, "P2": 5.0}                       # t_s
    assert (eec["hp_s"], eec["hs_s"], eec["gamma1"], eec["gamma2"]) == (28, 1, 0.9, 0.1)
    assert eec["terminal"] == "none" and eec["limit_weight"] == 0.0       # problem (7)'s J


def test_bcs_cycle_is_longer_than_the_machine_cycle_and_shrinks_with_its_band():
    full, half = bc_cycle_s(PAPER.problem), bc_cycle_s(PAPER.problem, band=0.5)
    assert 2 * 28 < full["P1"] < 4 * 28 and 28 < full["P2"] < full["P1"]  # "T_P > T"
    assert half["P1"] < full["P1"] and half["P2"] < full["P2"]


def test_every_point_of_the_study_has_one_run_and_no_run_is_planned_twice(tmp_path):
    for quick in (False, True):
        plan = plan_runs(quick, PAPER.problem, tmp_path / str(quick))
        flags = [sorted(params.items()) for params in plan.runs.values()]
        assert len(flags) == len({repr(f) for f in flags})   # distinct flags each
        for knob in KNOBS:
            for value in knob_values(knob, quick):
                for controller in knob.controllers:
                    assert plan.point(knob.key, value, controller) in plan.runs
    full = plan_runs(False, PAPER.problem, tmp_path / "full")
    assert full.cycles == 8 and full.ident_s == 600.0
    assert full.runs["eec-hpTP"]["hp"] == full.tp_s == round(bc_cycle_s(PAPER.problem)["P1"])
    assert full.point("load", 180.0, "bc") == "bc-dist"     # Table IV's runs serve the study
    assert full.point("hp", 42, "eec") == "eec-hp42"        # and Table II's
    assert full.point("band", 0.5, "eec") == "eec"          # BC's band leaves the EEC alone


def test_a_variant_config_changes_its_one_condition(tmp_path):
    plan = plan_runs(False, PAPER.problem, tmp_path)
    narrow = load_bench_config(plan.runs[plan.point("range", 0.5, "bc")]["config"])
    assert [(r.q_min, r.q_max) for r in narrow.problem.resources] == [(50.0, 100.0),
                                                                       (60.0, 120.0)]
    assert narrow.problem.sequence == PAPER.problem.sequence
    small = load_bench_config(plan.runs[plan.point("load", 70.0, "eec")]["config"])
    assert small.plant.disturbance.va == 70.0
    assert small.plant.disturbance.windows == PAPER.plant.disturbance.windows


def test_a_shifted_load_wraps_into_its_period():
    windows = shift_change(21.0)["plant"]["disturbance"]["windows"]
    assert windows == [[1.0, 9.0], [29.0, 41.0]]   # 36-44 s + 21 s = 57-65 s of 56
    assert sum(b - a for a, b in windows) == 20.0  # on as long as before
