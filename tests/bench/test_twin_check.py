"""``hil twin check`` of bench sessions, from the command line: a recording replayed into the
bench emulator, its relays switched tick by tick as recorded. The emulator that made a
recording is its exact twin (its recorded noise seed replayed); a twin whose P1 is a model
identified from ``hil bench identify`` passes; a model of the wrong gain fails (exit 1); what
cannot be checked is one line (exit 2)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import types
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from hil.controllers.ident.model_file import model_file_of
from hil.core.recording.reader import read_session
from tests.cli import hil_here, hil_in

pytestmark = [pytest.mark.slow]

P1_INPUTS = ["/ident/relays:P1", "/ident/relays:P1_start"]
PACKAGED_MODELS = Path(str(resources.files("hil.configs"))) / "models"


def hil(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``hil ARGS`` in a process of its own, from a folder outside the repository."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=180)


def relays_of(path: Path) -> list[dict[str, int]]:
    return [m for _, m in read_session(str(path)).topic("/bench/relays")]


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A user's folder: a BC run of the default bench (one cycle) with the plant's noise seed
    7, a 30 s PRBS experiment on P1 (seed 1) and the P1 model identified from it (its fit of
    the run: 99.63 %, as from 60 s)."""
    folder = tmp_path_factory.mktemp("twin")
    (folder / "seed7.toml").write_text("[plant]\nseed = 7\n")
    for args in (  # in this process: each start costs a second
            ("bench", "run", "--controller", "bc", "--cycles", "1", "--quiet", "--config",
             "seed7.toml", "--out", "run.mcap"),
            ("bench", "identify", "--relays", "P1", "--duration", "30", "--progress", "0",
             "--out", "P1.mcap"),
            ("identify", "P1.mcap", "--input", P1_INPUTS[0], "--input", P1_INPUTS[1],
             "--output", "/bench/power:va_l2", "--order", "3", "--detrend",
             "--no-feedthrough", "--out", "P1.json")):
        assert hil_in(folder, *args) == 0, args
    # P1 at twice its power (220 VA, the motor's 110 VA), reached in 0.3 s
    a = float(np.exp(-0.01 / 0.3))
    wrong = types.SimpleNamespace(A=np.diag([a, 0.0]), B=np.diag([1.0 - a, 0.0]),
                                  C=np.array([[220.0, 0.0]]), D=np.zeros((1, 2)), dt=0.01)
    (folder / "wrong.json").write_text(model_file_of(wrong, P1_INPUTS, ["/bench/power:va_l2"]))
    return folder


def test_a_recording_is_its_own_exact_twin_replayed_with_its_noise_seed(folder: Path) -> None:
    # seed 7 is not the packaged seed: only the recorded one gives the very same meter
    done = hil(folder, "twin", "check", "run.mcap", "--json", "--out", "run.png")
    assert done.returncode == 0, done.stderr
    check = json.loads(done.stdout)
    assert check["passed"] is True and check["min_fit_pct"] == 80.0
    assert check["session"] == "run.twin.mcap" and check["png"] == "run.png"
    # every load of the default bench is on L2: total_va and va_l2 are compared
    assert [o["name"] for o in check["outputs"]] == ["total_va", "va_l2"]
    samples = len(read_session(str(folder / "run.mcap")).topic("/bench/power"))
    for output in check["outputs"]:
        assert output["fit_pct"] == 100.0 and output["max_error"] == 0.0
        assert output["unit"] == "VA" and output["samples"] == samples == 2800
    # the relays, peripherals and machining sequence alike, switched at the recorded ticks
    twin = folder / "run.twin.mcap"
    assert relays_of(twin) == relays_of(folder / "run.mcap")
    assert read_session(str(twin)).metadata["session"]["kind"] == "bench"
    assert (folder / "run.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_an_identify_session_is_its_own_twin_too(folder: Path, capsys) -> None:
    done = hil_here(capsys, "twin", "check", "P1.mcap", "--twin-out", "P1-twin.mcap",
                    cwd=folder)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "total_va         fit  100.00 %" in done.stdout
    assert relays_of(folder / "P1-twin.mcap") == relays_of(folder / "P1.mcap")


def test_an_identified_load_model_makes_a_twin_and_a_wrong_gain_does_not(folder: Path,
                                                                       capsys) -> None:
    done = hil_here(capsys, "twin", "check", "run.mcap", "--model", "P1=P1.json",
                    "--min-fit", "95", "--json", "--twin-out", "model.mcap", cwd=folder)
    assert done.returncode == 0, done.stdout + done.stderr
    fits = {o["name"]: o for o in json.loads(done.stdout)["outputs"]}
    assert 95.0 <= fits["total_va"]["fit_pct"] < 100.0  # the model, not the emulator's motor
    config = json.loads(read_session(str(folder / "model.mcap")).metadata["config"]["json"])
    assert config["bench"]["plant"]["loads"]["P1"]["model"] == str(folder / "P1.json")

    done = hil_here(capsys, "twin", "check", "run.mcap", "--model", "P1=wrong.json",
                    "--min-fit", "95", "--twin-out", "wrong.mcap", cwd=folder)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "FAIL: every output's fit must reach 95 %" in done.stdout
    total = next(line for line in done.stdout.splitlines() if "total_va" in line)
    assert float(total.split("fit")[1].split("%")[0]) < 95.0


@pytest.mark.parametrize(("args", "message"), [
    (("--model", "X=P1.json"), "--model X=P1.json: 'X' is not a load of the recorded bench "
                               "(loads: M1, M2, P1, P2)"),
    (("--model", "P1.json"), "a bench twin's model is LOAD=F.json"),
    (("--model", "P1=absent.json"), "--model P1=absent.json: no such file absent.json"),
    (("--model", "P1=P1.json", "--model", "P1=wrong.json"), "load P1 is given a model twice"),
    (("--eds", "drive.eds"), "run.mcap is a bench session; a bench has no drive EDS"),
    (("--model", "M1=machining.json"), "reads relay 'M2'"),
])
def test_what_cannot_be_checked_is_one_line(folder: Path, capsys, args, message) -> None:
    (folder / "machining.json").write_bytes((PACKAGED_MODELS / "machining.json").read_bytes())
    done = hil_here(capsys, "twin", "check", "run.mcap", *args, "--twin-out", "bad.mcap",
                    cwd=folder)
    assert done.returncode == 2, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], done.stderr
    assert not (folder / "bad.mcap").exists()
