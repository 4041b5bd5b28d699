"""The bench emulator's loads from model files (``[plant.loads.NAME] model = "F.json"``): the
recorded power is what the model says of the relays ``hil bench identify`` switched, in lockstep
in-process and against ``hil emulate bench`` over Modbus TCP, from a folder outside the
repository (the emulator a process of its own, ``hil`` run in this process: tests/cli.py); the
machining model stands for M1 and M2 together, as the EEC reads it; a model
that cannot be the load is one line, exit 2."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import types
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from hil.bench.config import load_bench_config
from hil.controllers.bench.models import load_linear_model
from hil.controllers.ident.model_file import loads_model, model_file_of
from hil.core.recording.reader import read_session
from hil.emulators.bench.plant import BenchPlant, ModelLoadSpec
from tests.cli import hil_here

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

BASE_VA = 40.0  # [plant.base]: on L2, as every packaged load
QUIET = "[plant.meter]\nva_sigma = 0.0\nvoltage_sigma_v = 0.0\n"
IDENTIFY = ("bench", "identify", "--relays", "P1", "--duration", "30")
PACKAGED_MODELS = Path(str(resources.files("hil.configs"))) / "models"


def user_env() -> dict[str, str]:
    """A user's shell: hil installed, the repository not on the path."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


def pump_model(steady_va: float = 300.0, tau_s: float = 0.1, kick_va: float = 200.0,
               dt: float = 0.01, output: str = "/bench/power:va_l2") -> str:
    """A made-up P1: ``steady_va`` reached with ``tau_s``, and a kick at each switch-on that
    halves every step."""
    a = np.exp(-dt / tau_s)
    model = types.SimpleNamespace(A=np.diag([a, 0.5]), B=np.diag([1.0 - a, 1.0]),
                                  C=np.array([[steady_va, kick_va]]), D=np.zeros((1, 2)), dt=dt)
    return model_file_of(model, ["/ident/relays:P1", "/ident/relays:P1_start"], [output])


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> Path:
    """A user's folder: the model in ``models/`` and a bench config naming it beside it."""
    folder = tmp_path_factory.mktemp("bench")
    (folder / "models").mkdir()
    (folder / "models" / "pump.json").write_text(pump_model())
    (folder / "models" / "bench.toml").write_text(
        QUIET + '[plant.loads.P1]\nmodel = "pump.json"\n')
    (folder / "quiet.toml").write_text(QUIET)
    return folder


def expected_and_recorded(session: Path) -> tuple[np.ndarray, np.ndarray, int]:
    """The model's power for the relays the session wrote, the power it recorded on L2, and
    how many times P1 was switched on."""
    data = read_session(str(session))
    relays, power = data.arrays("/ident/relays"), data.arrays("/bench/power")
    inputs = np.column_stack([relays["P1"], relays["P1_start"]]).astype(float)
    expected = BASE_VA + loads_model(pump_model()).simulate(inputs)[:, 0]
    return expected, power["va_l2"], int(relays["P1_start"].sum())


def test_a_load_model_gives_the_recorded_power_in_lockstep(bench, capfd):
    done = hil_here(capfd, *IDENTIFY, "--config", "models/bench.toml", "--out", "model.mcap",
                    cwd=bench)
    assert done.returncode == 0, done.stderr
    expected, recorded, starts = expected_and_recorded(bench / "model.mcap")
    assert starts >= 1 and len(recorded) == 3000
    assert np.max(np.abs(recorded - expected)) < 1e-3  # VA: float32 registers
    built_in = hil_here(capfd, *IDENTIFY, "--config", "quiet.toml", "--out", "motor.mcap",
                        cwd=bench)
    assert built_in.returncode == 0, built_in.stderr
    _, motor, _ = expected_and_recorded(bench / "motor.mcap")
    assert np.max(np.abs(motor - recorded)) > 100.0  # the induction motor's inrush and steady


def test_hil_emulate_bench_serves_the_load_model(bench, capfd):
    """The standalone emulator reads the model beside its config; an experiment over Modbus
    TCP, in lockstep over the wire as a run is, records what the model says."""
    process = subprocess.Popen(
        [sys.executable, "-m", "hil", "emulate", "bench", "--tcp", "127.0.0.1:0", "--config",
         "models/bench.toml"], cwd=bench, env={**user_env(), "PYTHONUNBUFFERED": "1"},
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
    try:
        assert process.stdout is not None
        line = process.stdout.readline()
        url = re.search(r"listening on (modbus-tcp://\S+?) \(", line)
        assert url, line
        done = hil_here(capfd, *IDENTIFY, "--bench", url.group(1), "--config",
                        "models/bench.toml", "--out", "wire.mcap", cwd=bench)
        assert done.returncode == 0, done.stderr
    finally:
        process.send_signal(signal.SIGTERM)
        process.communicate(timeout=30)
    expected, recorded, starts = expected_and_recorded(bench / "wire.mcap")
    assert starts >= 1 and len(recorded) == 3000  # lockstep over the wire: every sample
    assert np.max(np.abs(recorded - expected)) < 1e-3


def test_the_machining_model_stands_for_m1_and_m2_as_the_eec_reads_it(tmp_path):
    """Both machining loads name the packaged machining model: one load, the model's output
    less its rest, for the relays and switch-ons of every step (the EEC's deviation form)."""
    machining = PACKAGED_MODELS / "machining.json"
    config = tmp_path / "bench.toml"
    config.write_text(f'[plant.loads.M1]\nmodel = "{machining}"\n'
                      f'[plant.loads.M2]\nmodel = "{machining}"\n')
    spec = load_bench_config(str(config)).plant
    models = [load for load in spec.loads if isinstance(load, ModelLoadSpec)]
    assert [load.name for load in models] == ["M1+M2"]
    plant = BenchPlant(spec)
    rng = np.random.default_rng(5)
    m1, m2 = (np.repeat(rng.integers(0, 2, 40), 25).astype(bool) for _ in range(2))
    inputs, va, before = [], [], (False, False)
    for now in zip(m1, m2, strict=True):
        plant.set_relay("M1", bool(now[0]))
        plant.set_relay("M2", bool(now[1]))
        plant.step()
        va.append(plant.load_va()["M1+M2"])
        inputs.append([now[0], now[0] and not before[0], now[1], now[1] and not before[1]])
        before = now
    eec = load_linear_model(machining)
    # the reading after a step sees the relays latched for it: the model's next sample; a
    # dip below rest (at a switch-off) gives no power back
    deviation = eec.simulate(np.asarray(inputs, float))[1:] - eec.rest_output
    expected = np.maximum(deviation, 0.0)
    assert deviation.min() < 0.0  # the packaged model dips, and the plant reads 0 there
    assert np.max(np.abs(np.asarray(va[:-1]) - expected)) < 1e-9 * np.max(np.abs(expected))
    assert np.max(va) > 300.0  # M1 and M2 together run at ~370 VA


BAD_LOADS = {
    "one-of-two": ('[plant.loads.M1]\nmodel = "{machining}"\n',
                   "key 'plant.loads.M1.model' ({machining}) reads relay 'M2', and no load "
                   "behind it names this file"),
    "period": ('[plant.loads.P1]\nmodel = "slow.json"\n',
               "key 'plant.loads.P1.model' ({folder}/slow.json) does not fit the plant: its "
               "period is 0.02 s: the plant steps every 0.01 s (plant.dt_s)"),
    "watts": ('[plant.loads.P1]\nmodel = "watts.json"\n',
              "key 'plant.loads.P1.model' is neither first_order nor induction_motor nor a load "
              "model: {folder}/watts.json: its outputs ['/bench/power:total_w'] are not one "
              "apparent power in VA"),
    "other-relay": ('[plant.loads.P2]\nmodel = "pump.json"\n',
                    "key 'plant.loads.P2.model' ({folder}/pump.json) reads relay 'P1', and no "
                    "load behind it names this file"),
    "missing": ('[plant.loads.P1]\nmodel = "nowhere.json"\n',
                "key 'plant.loads.P1.model' is neither first_order nor induction_motor nor a "
                "load model: {folder}/nowhere.json: no such model file"),
}


@pytest.mark.parametrize("case", BAD_LOADS)
def test_a_load_model_that_cannot_be_the_load_is_one_line_exit_2(tmp_path, capsys, case):
    text, problem = BAD_LOADS[case]
    names = {"machining": PACKAGED_MODELS / "machining.json", "folder": tmp_path}
    (tmp_path / "slow.json").write_text(pump_model(dt=0.02))
    (tmp_path / "watts.json").write_text(pump_model(output="/bench/power:total_w"))
    (tmp_path / "pump.json").write_text(pump_model())
    (tmp_path / "bad.toml").write_text(text.format(**names))
    done = hil_here(capsys, "emulate", "bench", "--tcp", "127.0.0.1:0", "--config", "bad.toml",
                    cwd=tmp_path)
    assert done.returncode == 2
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and done.stdout == "", done.stderr
    assert lines[0].startswith(f"hil: error: bad.toml: {problem.format(**names)}"), lines[0]


def test_an_emulator_process_is_handed_the_model_path_resolved(bench, tmp_path):
    """A real-time run gives its emulator process the run's tables in a temporary file: the
    model's path goes in absolute, so the process reads the file the config named."""
    config = load_bench_config(str(bench / "models" / "bench.toml"))
    tables = config.emulator_tables()
    assert tables["plant"]["loads"]["P1"]["model"] == str(bench / "models" / "pump.json")
    elsewhere = tmp_path / "run.toml"
    elsewhere.write_text(tomli_w.dumps(tables))
    spec = load_bench_config(str(elsewhere)).plant
    assert [load.model.source for load in spec.loads if isinstance(load, ModelLoadSpec)] == \
        [str(bench / "models" / "pump.json")]
