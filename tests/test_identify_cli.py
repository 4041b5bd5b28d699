"""``hil identify`` on session files recorded by a real Session + SimClock loop."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from hil.cli.main import main
from hil.controllers.ident import n4sid as ident
from hil.core.clock import SimClock
from hil.core.identify import load_model_file, parse_signal
from hil.core.loop import FunctionTask
from hil.core.session import Session
from hil.errors import ConfigError, UsageError

pytestmark = [pytest.mark.slow]

SCHEMA = {"type": "object", "title": "test.Message"}


def plant():
    """Motor power [VA] after its relay closes: inrush peak, ~1000 VA steady (0.01 s steps)."""
    poles = np.exp(-0.01 / np.array([0.02, 0.05, 0.3]))
    gains = np.array([2000.0, 800.0, -1800.0])
    return np.diag(poles), np.ones((3, 1)), (gains * (1 - poles))[None, :], np.zeros((1, 1))


def record(
    path: Path, ticks: int, seed: int = 1, nan_at: int | None = None, drop: tuple[int, ...] = ()
) -> None:
    """A relay-switched plant run in lockstep: relays every tick, relay changes only when they
    change, power with 10 VA noise (flat and nested fields), except at the ticks in ``drop``."""
    A, B, C, _ = plant()
    rng = np.random.default_rng(seed)
    session = Session(str(path), SimClock(), 0.01, kind="ident-test", handle_signals=False)
    relays = session.topic("/bench/relays", SCHEMA)
    changes = session.topic("/bench/relay_changes", SCHEMA)
    power = session.topic("/bench/power", SCHEMA)
    state = {"x": np.zeros(3), "u": 0.0, "hold": 20, "k": 0}

    def step(t_ns):
        if state["hold"] == 0:
            state["u"] = 1.0 - state["u"]
            state["hold"] = int(rng.integers(30, 150))
            changes.log(t_ns, {"P1": bool(state["u"])})
        elif state["k"] == 0:
            changes.log(t_ns, {"P1": False})
        state["hold"] -= 1
        y = float(C[0] @ state["x"]) + 10.0 * rng.normal()
        if state["k"] == nan_at:
            y = math.nan
        relays.log(t_ns, {"P1": bool(state["u"]), "P2": False, "coils": [0, 0, state["u"], 0]})
        if state["k"] not in drop:
            power.log(t_ns, {"L1": 0.0, "L2": y, "phases": [{"va": 0.0}, {"va": y}, {"va": 0.0}]})
        state["x"] = A @ state["x"] + B[:, 0] * state["u"]
        state["k"] += 1

    session.add_task(FunctionTask("plant", 1, write=step))
    session.run(max_ticks=ticks)
    session.close()


@pytest.fixture(scope="module")
def session_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("ident") / "relay_test.mcap"
    record(path, 3000)
    return path


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(["identify", *map(str, argv)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_identify_json_prints_order_fit_matrices_and_writes_the_model_file(
    session_file, tmp_path, capsys
):
    out = tmp_path / "models" / "p1.json"
    code, stdout, stderr = run_cli(
        capsys, session_file, "--input", "/bench/relays:P1", "--output", "/bench/power:L2",
        "--order", "3", "--json", "--out", out,
    )
    assert code == 0, stderr
    result = json.loads(stdout)
    assert result["order"] == 3 and result["fit_pct"] >= 95.0
    assert result["dt"] == pytest.approx(0.01)
    assert np.array(result["A"]).shape == (3, 3) and np.array(result["B"]).shape == (3, 1)
    assert np.array(result["C"]).shape == (1, 3) and np.array(result["D"]).shape == (1, 1)
    assert np.array(result["K"]).shape == (3, 1)
    assert result["model"] == str(out) and result["irregular_intervals"] == 0
    assert result["samples"] == {"total": 3000, "train": 2100, "test": 900}

    model = load_model_file(out)
    assert model.inputs == ("/bench/relays:P1",) and model.outputs == ("/bench/power:L2",)
    assert model.fit_pct == pytest.approx(result["fit_pct"])
    A, B, C, D = plant()
    dc_true = (C @ np.linalg.solve(np.eye(3) - A, B))[0, 0]
    dc_model = (model.C @ np.linalg.solve(np.eye(3) - model.A, model.B) + model.D)[0, 0]
    assert dc_model == pytest.approx(dc_true, rel=0.02)
    true_markov = ident.markov_parameters(A, B, C, D, 50)
    est_markov = ident.markov_parameters(model.A, model.B, model.C, model.D, 50)
    assert np.max(np.abs(est_markov - true_markov)) < 0.05 * np.max(np.abs(true_markov))
    # the command that regenerates the file is written into it, and does regenerate it
    assert model.command.startswith(f"hil identify {session_file} --input /bench/relays:P1 ")
    assert model.block_rows_selection["method"] == "bic"  # not given: chosen, and spelled out
    assert f"--order 3 --block-rows {model.block_rows} --train-fraction 0.7" in model.command
    again = tmp_path / "again.json"
    argv = model.command.split()[1:]
    argv[argv.index("--out") + 1] = str(again)
    assert main(argv) == 0
    capsys.readouterr()
    assert np.array_equal(load_model_file(again).A, model.A)


def test_nested_paths_and_sparse_logs_give_the_same_model(session_file, tmp_path, capsys):
    """coils[2] / phases[1].va read the same numbers as P1 / L2; a topic logged only on change
    holds its value until the next message (zero-order hold), so the data are identical."""
    models = []
    for k, (signal_in, signal_out) in enumerate([
        ("/bench/relays:P1", "/bench/power:L2"),
        ("/bench/relays:coils[2]", "/bench/power:phases[1].va"),
        ("/bench/relay_changes:P1", "/bench/power:L2"),
    ]):
        out = tmp_path / f"m{k}.json"
        code, _, stderr = run_cli(capsys, session_file, "--input", signal_in, "--output",
                                  signal_out, "--order", "3", "--out", out)
        assert code == 0, stderr
        models.append(load_model_file(out))
    for model in models[1:]:
        assert np.array_equal(model.A, models[0].A) and np.array_equal(model.B, models[0].B)
        assert model.fit_pct == models[0].fit_pct


def test_without_order_the_text_report_shows_the_selected_order(session_file, tmp_path, capsys):
    out = tmp_path / "auto.json"
    code, stdout, stderr = run_cli(capsys, session_file, "--input", "/bench/relays:P1",
                                   "--output", "/bench/power:L2", "--out", out)
    assert code == 0, stderr
    assert "order:        3 (selected by BIC over orders 1-8)" in stdout
    fit = float(stdout.split("fit_pct:")[1].split("%")[0])
    assert fit >= 95.0
    assert "A = [[" in stdout and "regenerate with: hil identify" in stdout
    assert load_model_file(out).order_selection["method"] == "bic"


def test_default_model_file_goes_next_to_the_session(tmp_path, capsys):
    session = tmp_path / "run.mcap"
    record(session, 1500, seed=3)
    code, stdout, _ = run_cli(capsys, session, "--input", "/bench/relays:P1", "--output",
                              "/bench/power:L2", "--order", "3", "--json")
    assert code == 0
    assert json.loads(stdout)["model"] == str(tmp_path / "run.model.json")
    assert load_model_file(tmp_path / "run.model.json").order == 3


@pytest.mark.parametrize(
    ("signals", "message"),
    [
        (["--input", "/bench/nope:P1", "--output", "/bench/power:L2"],
         "/bench/nope:P1: unknown topic '/bench/nope'"),
        (["--input", "/bench/relays:P9", "--output", "/bench/power:L2"],
         "unknown field 'P9' (fields of the message: P1, P2, coils)"),
        (["--input", "/bench/relays:coils[7]", "--output", "/bench/power:L2"],
         "index [7] out of range (coils has 4 elements)"),
        (["--input", "/bench/relays:coils", "--output", "/bench/power:L2"],
         "is a list, not a number"),
        (["--input", "/bench/relays:coils[x]", "--output", "/bench/power:L2"],
         "bad field path 'coils[x]' at character 6"),
        (["--input", "P1", "--output", "/bench/power:L2"], "expected TOPIC:FIELD"),
        (["--input", "/bench/relays:P2", "--output", "/bench/power:L2"],
         "input '/bench/relays:P2' is constant (0)"),
        (["--output", "/bench/power:L2"],
         "name the signals with --input TOPIC:FIELD and --output TOPIC:FIELD; signals in "
         "this file: /bench/power: L1, L2, phases[0].va"),
        (["--input", "/bench/relays:P1", "--output", "/bench/power:L2", "--order", "30",
          "--block-rows", "15"], "order 30 needs at least 31 block rows"),
    ],
)
def test_bad_signals_are_one_clear_error(session_file, tmp_path, capsys, signals, message):
    code, stdout, stderr = run_cli(capsys, session_file, *signals, "--out", tmp_path / "m.json")
    assert code == 2 and stdout == ""
    assert stderr.startswith("hil: error: ") and message in stderr, stderr
    assert "Traceback" not in stderr and stderr.count("\n") == 1
    assert not (tmp_path / "m.json").exists()


def test_nan_in_the_log_is_a_clear_error_with_its_time(tmp_path, capsys):
    session = tmp_path / "nan.mcap"
    record(session, 1500, nan_at=700)
    code, _, stderr = run_cli(capsys, session, "--input", "/bench/relays:P1", "--output",
                              "/bench/power:L2", "--order", "3")
    assert code == 2
    assert stderr.startswith("hil: error: /bench/power:L2: 1 NaN/missing value(s) in the log, "
                             "first at t = 7.000 s (message 700 of 1500)")


def test_dropped_output_samples_are_counted_and_warned_about(tmp_path, capsys):
    session = tmp_path / "gaps.mcap"
    record(session, 1500, drop=(400, 900, 901))
    code, stdout, stderr = run_cli(capsys, session, "--input", "/bench/relays:P1", "--output",
                                   "/bench/power:L2", "--order", "3", "--json")
    assert code == 0
    result = json.loads(stdout)
    assert result["irregular_intervals"] == 2 and result["samples"]["total"] == 1497
    assert result["dt"] == pytest.approx(0.01)
    assert stderr.startswith("hil: warning: 2 of 1496 sampling intervals of /bench/power:L2 "
                             "differ from dt = 0.01 s")


def test_too_few_samples_for_the_block_rows_is_a_clear_error(tmp_path, capsys):
    session = tmp_path / "short.mcap"
    record(session, 100)
    code, _, stderr = run_cli(capsys, session, "--input", "/bench/relays:P1", "--output",
                              "/bench/power:L2", "--order", "3")
    assert code == 2
    assert "too few samples: the training part (0.7 of 100) has 70 samples" in stderr
    assert "need at least 89" in stderr
    code, _, stderr = run_cli(capsys, session, "--input", "/bench/relays:P1", "--output",
                              "/bench/power:L2", "--order", "3", "--block-rows", "4")
    assert code == 0, stderr


def test_train_fraction_out_of_range_is_an_argument_error(session_file, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["identify", str(session_file), "--input", "/bench/relays:P1", "--output",
              "/bench/power:L2", "--train-fraction", "1.5"])
    assert exc.value.code == 2
    assert "expected a number in (0, 1), got 1.5" in capsys.readouterr().err


def test_model_file_never_overwrites_the_session(session_file, capsys):
    size = session_file.stat().st_size
    code, _, stderr = run_cli(capsys, session_file, "--input", "/bench/relays:P1", "--output",
                              "/bench/power:L2", "--out", session_file)
    assert code == 2 and "is the session file itself" in stderr
    assert session_file.stat().st_size == size


def test_missing_session_file_is_a_clear_error(tmp_path, capsys):
    code, _, stderr = run_cli(capsys, tmp_path / "none.mcap", "--input", "/a:b", "--output",
                              "/c:d")
    assert code == 2 and "no such session file" in stderr


def test_broken_model_files_raise_config_errors(tmp_path):
    with pytest.raises(ConfigError, match=r"model file .*missing\.json: No such file"):
        load_model_file(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "hil.ident.state-space", "version": 1}')
    with pytest.raises(ConfigError, match=r"bad\.json: model file lacks the key"):
        load_model_file(bad)


def test_signal_paths_parse_keys_and_indexes():
    assert parse_signal("/bench/power:phases[1].va").path == ("phases", 1, "va")
    assert parse_signal("/ns:topic:a.b[0][2]").topic == "/ns:topic"
    assert parse_signal("/ns:topic:a.b[0][2]").path == ("a", "b", 0, 2)
    for bad in ("/t:a..b", "/t:a.", "/t:[x]", "/t:", ":a"):
        with pytest.raises(UsageError):
            parse_signal(bad)
