"""``hil bench identify`` over the emulated bench (Modbus TCP on loopback, lockstep), then
``hil identify`` on the recorded session: a well-formed PRBS experiment and a useful model."""

from __future__ import annotations

import json
import shlex

import numpy as np
import pytest

from hil.cli.main import main
from hil.core.recording.reader import read_session

pytestmark = [pytest.mark.timeout(60), pytest.mark.slow]

DWELL_P1_S = 5.0  # hil/configs/bench.toml


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def identify_json(capsys, argv: list[str]) -> dict:
    code, out, err = run_cli(capsys, *argv, "--json")
    assert code == 0, err
    return json.loads(out)


def test_prbs_experiment_then_identification(tmp_path, capsys):
    session = tmp_path / "p1.mcap"
    code, out, err = run_cli(capsys, "bench", "identify", "--relays", "P1", "--duration", "60",
                             "--seed", "6", "--progress", "20", "--out", str(session),
                             "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert "t =   20.0 / 60 s" in err and "t =   40.0 / 60 s" in err  # progress on stderr
    assert summary["clock"] == "sim" and summary["stop_reason"] == "completed"
    assert summary["min_hold_s"] == {"P1": DWELL_P1_S}
    assert summary["deferred_requests"] == 0 and summary["failed_writes"] == 0
    assert summary["switches"]["P1"] >= 6

    data = read_session(str(session))
    assert data.metadata["session"]["kind"] == "bench-identify"
    events = [m for _, m in data.topic("/events")]
    assert not [e for e in events if e["kind"] == "relay.deferred"]

    # the PRBS as written, its switch-on events, and the sampler seeing it one sample later
    prbs = data.topic("/ident/relays")
    written = np.array([m["P1"] for _, m in prbs])
    starts = np.array([m["P1_start"] for _, m in prbs])
    seen = np.array([m["P1"] for _, m in data.topic("/bench/relays")])
    assert len(written) == len(seen) == 6000
    np.testing.assert_array_equal(seen[1:], written[:-1])
    rising = np.flatnonzero(np.diff(np.concatenate([[0], written])) == 1)
    np.testing.assert_array_equal(np.flatnonzero(starts), rising)
    changes = np.flatnonzero(np.diff(written)) + 1
    assert np.min(np.diff(changes)) * 0.01 >= DWELL_P1_S - 1e-9  # every hold >= the dwell

    # the printed command: (relay, switch-on event) -> VA of phase L2
    (entry,) = summary["identify_commands"]
    assert entry["target"] == "P1"
    argv = shlex.split(entry["command"])
    assert argv[:3] == ["hil", "identify", str(session)]
    assert "/bench/power:va_l2" in argv
    two_input = identify_json(capsys, argv[1:])
    assert two_input["order"] == 3
    assert two_input["fit_pct"] >= 90.0, two_input["fit_pct"]
    # the model file names the experiment that recorded its data
    assert two_input["experiment"] == (f"hil bench identify --relays P1 --duration 60 --seed 6 "
                                       f"--progress 20 --out {session} --json")

    # the one-input form: a linear model of the relay alone cannot hold the inrush
    one_input = identify_json(capsys, [
        "identify", str(session), "--input", "/bench/relays:P1", "--output",
        "/bench/power:va_l2", "--order", "3", "--detrend", "--out", str(tmp_path / "one.json")])
    assert one_input["fit_pct"] < two_input["fit_pct"]
    print(f"P1 held-out fit: two inputs {two_input['fit_pct']:.2f} %, "
          f"relay only {one_input['fit_pct']:.2f} %")


@pytest.mark.parametrize("argv, message", [
    (["--relays", "P1", "--min-hold", "2"], "--min-hold 2 s is shorter than the dwell of P1"),
    (["--relays", "P1,X9"], "unknown relay(s) X9"),
    (["--relays", "M1", "--machining", "sequence"], "played by --machining sequence"),
    (["--relays", "none"], "nothing to switch"),
    (["--output-quantity", "va_l9"], "'va_l9' is not polled"),
])
def test_bad_input_is_one_clear_line(argv, message, tmp_path, capsys):
    code, _out, err = run_cli(capsys, "bench", "identify", *argv, "--duration", "5",
                             "--out", str(tmp_path / "x.mcap"))
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("hil: error: ") and message in err, err
    assert not (tmp_path / "x.mcap").exists()
