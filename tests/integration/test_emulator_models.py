"""The emulators run identified models: a drive emulator whose axis is a model file (``[emulator]
model``, ``--drive 'emulated?model=F'``, ``hil emulate drive --model``) and a bench emulator
whose load is one (``[plant.loads.NAME] model``), from the command line in a folder outside
the repository. The machine is a different axis (the published one with its resonance moved
and its gain changed, written by :func:`axis_model_file`): a run's recorded positions are that
axis' (the plant stepped directly with the recorded currents), not the default's. A run of
the default axis and the standalone emulator are processes of their own; the variants run
``hil`` in this process (tests/cli.py), from the same folder."""

from __future__ import annotations

import os
import re
import select
import signal
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from hil.controllers.ident.model_file import loads_model, model_file_of
from hil.controllers.servo.model import StateSpaceModel, published_axis_model, resampled
from hil.core.recording.reader import read_session
from hil.emulators.drive.axis_model import axis_model_file
from hil.emulators.drive.plant import AxisPlant
from tests.cli import hil_here

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

INCREMENT_DEG = 360.0 / 2**20  # the emulated encoder's resolution
RUN = ("servo", "run", "--controller", "pid", "--reference", "sine:amplitude=20,frequency=7",
       "--duration", "0.3")


def resonance_hz(model: StateSpaceModel) -> float:
    """The frequency of the axis' one complex pole pair [Hz]."""
    poles = np.linalg.eigvals(model.A)
    pair = poles[np.abs(poles.imag) > 1e-9]
    return float(np.abs(np.angle(pair[0]))) / (2 * np.pi * model.dt)


def other_axis(frequency_scale: float = 0.6, gain: float = 1.5) -> StateSpaceModel:
    """The published axis with its resonance at ``frequency_scale`` times its frequency (the
    damping kept) and ``gain`` times its input gain."""
    axis = published_axis_model()
    poles, right = np.linalg.eig(axis.A)
    left_poles, left = np.linalg.eig(axis.A.T)
    A = axis.A.astype(complex)
    for i in np.flatnonzero(np.abs(poles.imag) > 1e-9):
        w = left[:, np.argmin(np.abs(left_poles - poles[i]))]
        s = np.log(poles[i]) / axis.dt
        moved = np.exp(complex(s.real, s.imag * frequency_scale) * axis.dt)
        A += (moved - poles[i]) * np.outer(right[:, i], w) / (w @ right[:, i])
    return StateSpaceModel(A=A.real, B=axis.B * gain, C=axis.C, D=axis.D, dt=axis.dt)


def user_env() -> dict[str, str]:
    """A user's shell: hil installed, the repository not on the path."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


def hil(folder: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=folder, env=user_env(),
                          capture_output=True, text=True, timeout=timeout)


def positions_and_currents(session: Path) -> tuple[np.ndarray, np.ndarray]:
    feedback = read_session(str(session)).arrays("/drive/feedback")
    return feedback["position_deg"], feedback["current_mA"]


def simulated(model: StateSpaceModel | None, currents: np.ndarray) -> np.ndarray:
    """The axis stepped directly with the currents the drive applied, one cycle each."""
    plant = AxisPlant(model)
    out = []
    for current in currents:
        plant.step(float(current))
        out.append(plant.position_deg)
    return np.asarray(out)


@pytest.fixture(scope="module")
def machine(tmp_path_factory) -> Path:
    """A user's folder: the other axis' model file in ``models/``, a drive.toml naming it
    beside it, and a lockstep run of the default axis."""
    folder = tmp_path_factory.mktemp("machine")
    (folder / "models").mkdir()
    (folder / "models" / "other.json").write_text(axis_model_file(other_axis()))
    (folder / "models" / "drive.toml").write_text('[emulator]\nmodel = "other.json"\n')
    done = hil(folder, *RUN, "--out", "default.mcap")
    assert done.returncode == 0, done.stderr
    return folder


def test_the_other_axis_has_its_resonance_moved():
    assert resonance_hz(published_axis_model()) == pytest.approx(439.8, abs=0.1)
    assert resonance_hz(other_axis()) == pytest.approx(0.6 * 439.8, abs=0.1)


@pytest.mark.parametrize("where", ["config", "url"])
def test_a_lockstep_run_moves_the_model_files_axis(machine, capfd, where):
    """The key (its path beside the config file) or the URL (its path from the working
    folder): the positions are the other axis', within the encoder's resolution."""
    out = f"other-{where}.mcap"
    given = ["--config", "models/drive.toml"] if where == "config" \
        else ["--drive", "emulated?model=models/other.json"]
    done = hil_here(capfd, *RUN, *given, "--out", out, cwd=machine)
    assert done.returncode == 0, done.stderr
    positions, currents = positions_and_currents(machine / out)
    default, _ = positions_and_currents(machine / "default.mcap")
    assert len(positions) == len(default) == 600
    assert np.max(np.abs(positions - default)) > 1.0  # deg: another axis
    assert np.max(np.abs(positions - simulated(other_axis(), currents))) <= INCREMENT_DEG
    assert np.max(np.abs(positions - simulated(None, currents))) > 100 * INCREMENT_DEG


def test_the_published_axis_as_a_model_file_runs_as_the_default(machine, capfd):
    (machine / "published.json").write_text(axis_model_file(published_axis_model()))
    done = hil_here(capfd, *RUN, "--drive", "emulated?model=published.json", "--out", "pub.mcap",
                    cwd=machine)
    assert done.returncode == 0, done.stderr
    positions, _ = positions_and_currents(machine / "pub.mcap")
    default, _ = positions_and_currents(machine / "default.mcap")
    assert np.array_equal(positions, default)


def test_a_model_steps_as_often_as_its_period_fits_in_the_cycle(machine, capfd):
    """A 1000 us cycle: the published axis' 500 us file steps twice per SYNC, as the default
    axis does; the same axis sampled every 1000 us steps once, to the same positions."""
    axis = published_axis_model()
    (machine / "p500.json").write_text(axis_model_file(axis))
    (machine / "p1000.json").write_text(axis_model_file(resampled(axis, 1e-3)))
    (machine / "cycle.toml").write_text("[master]\ncycle_period_us = 1000\n")
    positions = {}
    for name in ("default", "p500", "p1000"):
        drive = "emulated" if name == "default" else f"emulated?model={name}.json"
        done = hil_here(capfd, *RUN, "--param", "ti_us=8000", "--config", "cycle.toml",
                        "--drive", drive, "--out", f"cycle-{name}.mcap", cwd=machine)
        assert done.returncode == 0, done.stderr
        positions[name], _ = positions_and_currents(machine / f"cycle-{name}.mcap")
    assert len(positions["default"]) == 300
    assert np.array_equal(positions["p500"], positions["default"])
    assert np.max(np.abs(positions["p1000"] - positions["default"])) <= INCREMENT_DEG


def axis_file(**change) -> str:
    """The other axis' model file, a field of it changed (``None``: removed)."""
    model = loads_model(axis_model_file(other_axis()))
    data = {"inputs": list(model.inputs), "outputs": list(model.outputs), "dt": model.dt}
    data.update(change)
    known = types.SimpleNamespace(A=model.A, B=np.tile(model.B, len(data["inputs"])),
                                  C=np.tile(model.C, (len(data["outputs"]), 1)),
                                  D=np.zeros((len(data["outputs"]), len(data["inputs"]))),
                                  dt=data["dt"])
    return model_file_of(known, data["inputs"], data["outputs"])


BAD_AXES = {
    "not-a-model": ('{"format": "something else"}',
                    "is no axis model: {path}: not a model file: 'format' must be "
                    "'hil.ident.state-space'"),
    "two-inputs": (axis_file(inputs=["/drive/feedback:command_mA", "/drive/command:command_mA"]),
                   "is no axis model: {path}: has 2 input(s) and 1 output(s); an axis model "
                   "has one input, a current in mA"),
    "input-not-mA": (axis_file(inputs=["/drive/feedback:velocity_deg_s"]),
                     "is no axis model: {path}: its input '/drive/feedback:velocity_deg_s' is "
                     "not a current in mA (its field must end in _mA"),
    "output-not-deg": (axis_file(outputs=["/drive/feedback:current_mA"]),
                       "is no axis model: {path}: its output '/drive/feedback:current_mA' is "
                       "not a position in deg (its field must end in _deg"),
    "period": (axis_file(dt=0.0003),
               "({path}) does not fit master.cycle_period_us: its period is 300 us: the "
               "drive's cycle of 500 us must be a whole multiple of it"),
    "missing": (None, "is no axis model: {path}: no such model file"),
}


@pytest.mark.parametrize("case", BAD_AXES)
def test_a_bad_axis_model_is_one_line_exit_2(tmp_path, capsys, case):
    text, problem = BAD_AXES[case]
    model = tmp_path / f"{case}.json"
    if text is not None:
        model.write_text(text)
    (tmp_path / "drive.toml").write_text(f'[emulator]\nmodel = "{case}.json"\n')
    done = hil_here(capsys, *RUN, "--config", "drive.toml", cwd=tmp_path)
    assert done.returncode == 2
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"hil: error: drive.toml: key 'emulator.model' "
                               f"{problem.format(path=model)}"), lines[0]


def test_the_url_takes_the_model_key_only(tmp_path, capsys):
    done = hil_here(capsys, *RUN, "--drive", "emulated?axis=x.json", cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr == ("hil: error: --drive 'emulated?axis=x.json': 'axis=x.json' is not a "
                           "key of the emulated drive (it takes model=F.json: its axis as a "
                           "model file)\n")


def start_emulator(folder: Path, *args: str) -> tuple[subprocess.Popen[str], str]:
    """``hil emulate drive --socketcand 127.0.0.1:0 ARGS`` and its first line of output."""
    process = subprocess.Popen(
        [sys.executable, "-m", "hil", "emulate", "drive", "--socketcand", "127.0.0.1:0",
         *args], cwd=folder, env={**user_env(), "PYTHONUNBUFFERED": "1"},
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert process.stdout is not None
    ready, _, _ = select.select([process.stdout], [], [], 60)
    return process, process.stdout.readline() if ready else ""


def stop(process: subprocess.Popen[str]) -> str:
    """Stop it (SIGTERM, bounded) and return what it wrote to stderr."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=30)
    return err


def test_hil_emulate_drive_runs_the_model_given_by_its_flag(machine, capfd):
    """The standalone emulator with --model: a lockstep run over socketcand moves the other
    axis; a bad model is refused in one line."""
    process, line = start_emulator(machine, "--model", "models/other.json")
    try:
        port = re.search(r"socketcand 127\.0\.0\.1:(\d+) ", line)
        assert port, line
        done = hil_here(capfd, *RUN, "--drive", f"socketcand://127.0.0.1:{port.group(1)}",
                        "--out", "wire.mcap", cwd=machine)
        assert done.returncode == 0, done.stderr
    finally:
        stop(process)
    positions, currents = positions_and_currents(machine / "wire.mcap")
    assert np.max(np.abs(positions - simulated(other_axis(), currents))) <= INCREMENT_DEG
    (machine / "two.json").write_text(BAD_AXES["two-inputs"][0])
    refused, line = start_emulator(machine, "--model", "two.json")
    err = stop(refused)
    assert refused.returncode == 2 and line == ""
    assert err.startswith(f"hil: error: --model: key 'emulator.model' is no axis model: "
                          f"{machine / 'two.json'}: has 2 input(s)") and err.count("\n") == 1


@pytest.mark.realtime
def test_a_real_time_run_hands_the_model_to_the_emulator_process(tmp_path, capsys):
    """--realtime: the emulator in a process of its own reads the model file named beside the
    config (its rest position 90 deg: the first position the run records)."""
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "offset.json").write_text(model_file_of(
        loads_model(axis_model_file(other_axis())), ["/drive/feedback:command_mA"],
        ["/drive/feedback:position_deg"], y_offset=[90.0]))
    (tmp_path / "cfg" / "drive.toml").write_text('[emulator]\nmodel = "offset.json"\n')
    done = hil_here(capsys, "servo", "run", "--controller", "pid", "--reference", "hold",
                    "--from-here", "--duration", "0.1", "--realtime", "--config",
                    "cfg/drive.toml", "--out", "rt.mcap", cwd=tmp_path)
    assert done.returncode in (0, 3), done.stderr  # 3: a loaded machine answered late
    positions, _ = positions_and_currents(tmp_path / "rt.mcap")
    assert positions[0] == pytest.approx(90.0, abs=INCREMENT_DEG)
