"""How a sweep's trials are recorded: on Ray in the trial's own process (no writer process per
trial: every core already runs a trial), one after another (``--serial``) with a writer
process; a trial in real time keeps its writer process whatever the engine. Either way a trial
records the same session."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import pytest

from hil.cli.servo import add_run_arguments
from hil.sweep.engine import Engine
from hil.sweep.space import expand
from hil.sweep.sweep import Sweep, job_of
from hil.sweep.trial import TrialJob, experiment_of, run_trial
from tests.session_digest import session_digest

pytestmark = [pytest.mark.timeout(120)]


def servo_flags(*argv: str) -> dict:
    parser = argparse.ArgumentParser()
    add_run_arguments(parser)
    return vars(parser.parse_args(["--controller", "pid", "--duration", "0.2", *argv]))


def sweep_on(engine: Engine, out: Path) -> Sweep:
    trials = expand({"umax": [500.0, 800.0]})
    return Sweep("servo", servo_flags(), ("umax",), tuple(trials), out, engine)


def test_ray_trials_record_in_their_process_serial_ones_with_a_writer_process(tmp_path):
    on_ray = [job_of(sweep_on(Engine(workers=2), tmp_path), t) for t in
              sweep_on(Engine(), tmp_path).trials]
    serial = [job_of(sweep_on(Engine(serial=True), tmp_path), t) for t in
              sweep_on(Engine(), tmp_path).trials]
    assert [job.in_process for job in on_ray] == [True, True]
    assert [job.in_process for job in serial] == [False, False]
    assert all(experiment_of(job).options.recording.in_process for job in on_ray)
    assert not any(experiment_of(job).options.recording.in_process for job in serial)


def test_a_trial_in_real_time_keeps_its_writer_process(tmp_path):
    job = TrialJob("servo", servo_flags("--realtime"), "t", {}, str(tmp_path / "t.mcap"),
                   in_process=True)
    experiment = experiment_of(job)
    assert experiment.options.realtime and not experiment.options.recording.in_process


@pytest.mark.slow
def test_a_trial_recorded_in_its_process_records_the_session_of_one_with_a_writer(tmp_path):
    job = TrialJob("servo", servo_flags(), "t", {"umax": 600.0}, str(tmp_path / "p.mcap"))
    rows = [run_trial(job), run_trial(replace(job, in_process=True,
                                              mcap=str(tmp_path / "i.mcap")))]
    assert [row["status"] for row in rows] == ["ok", "ok"]
    assert rows[0]["kpis"]["rms_error_deg"] == rows[1]["kpis"]["rms_error_deg"]
    assert rows[1]["kpis"]["umax_mA"] == 600.0
    assert session_digest(str(tmp_path / "i.mcap")) == session_digest(str(tmp_path / "p.mcap"))
