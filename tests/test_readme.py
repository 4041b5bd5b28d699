"""The README's code, run as a user would, from a folder outside the repository: its Python
blocks (the controllers file, the API tour; the pytest example runs five times over on a busy
machine in tests/integration/test_busy_machine.py), its `hil` commands checked
against the parser (every flag it shows exists) and the limit examples run for the exit status
the README promises (the first from a ``hil`` process, the others from the command line run in
this process). A README that drifts from the code fails here."""

import os
import re
import shlex
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from hil.cli.main import build_parser, main

pytestmark = [pytest.mark.timeout(240), pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
ENV = dict(os.environ, PYTHONPATH=str(ROOT))


def blocks(language):
    """The README's code blocks in ``language``, in order (those indented in a list too)."""
    found = re.findall(rf"^( *)```{language}\n(.*?)^ *```", README, re.M | re.S)
    return [textwrap.dedent("".join(line.removeprefix(indent) for line in
                                    block.splitlines(keepends=True)))
            for indent, block in found]


def block(language, containing):
    """The one README code block in ``language`` that holds ``containing`` (a block's place
    among the others changes as the README grows)."""
    [found] = [text for text in blocks(language) if containing in text]
    return found


def hil_commands():
    """Every `hil ...` command of the sh blocks, continuation lines joined."""
    commands = []
    for block in blocks("sh"):
        for line in block.replace("\\\n", " ").splitlines():
            line = " ".join(line.split("  #")[0].split())
            if line.startswith("hil "):
                commands.append(line)
    return commands


@pytest.fixture
def user_folder(tmp_path):
    """A folder of the user's: the README's controllers file in it, nothing of the repo."""
    (tmp_path / "my_controllers.py").write_text(block("python", "class ThresholdRelays:"))
    return tmp_path


def test_every_hil_command_of_the_readme_parses():
    commands = hil_commands()
    assert len(commands) >= 10
    parser = build_parser()
    for command in commands:
        argv = shlex.split(command)[1:]
        if "--help" in argv:
            continue  # prints and exits 0 by design
        try:
            parser.parse_args(argv)
        except SystemExit:
            pytest.fail(f"README command does not parse: {command}")


@pytest.mark.parametrize(("command", "status", "outside"), [
    ("hil servo run --controller pid --limit 'rms_error_deg<=0.5' --limit "
     "'abs_command_mA<=1000' --junit servo.xml", 0, True),
    ("hil servo run --controller pid --limit 'max_error_deg<=0.1'", 1, False),
    ("hil servo run --controller my_controllers.py:PdPosition --param kp=400 "
     "--reference sine:amplitude=2,frequency=1 --duration 2", 0, False),
])
def test_the_readme_commands_give_the_status_it_says(user_folder, monkeypatch, capfd, command,
                                                     status, outside):
    assert command in hil_commands()
    argv = shlex.split(command)[1:]
    if outside:
        done = subprocess.run([sys.executable, "-m", "hil", *argv], cwd=user_folder,
                              capture_output=True, text=True, env=ENV, timeout=120,
                              check=False)
        assert done.returncode == status, done.stderr
    else:
        monkeypatch.chdir(user_folder)
        assert main(argv) == status, capfd.readouterr().err


def test_the_api_tour_runs(user_folder):
    script = "from my_controllers import PdPosition, ThresholdRelays\n" + \
        block("python", "kpis = api.run_bench(ThresholdRelays")
    (user_folder / "tour.py").write_text(script)
    done = subprocess.run([sys.executable, "tour.py"], cwd=user_folder, capture_output=True,
                          text=True, env=ENV, timeout=180, check=False)
    assert done.returncode == 0, done.stderr
    rms, passed, mcap = done.stdout.splitlines()[0].split()
    assert float(rms) < 0.5 and passed == "True" and Path(user_folder, mcap).exists()


def test_the_several_axes_example_moves_each_axis_its_own_way(user_folder):
    (user_folder / "axes.py").write_text(block("python", "CanDriveMaster"))
    done = subprocess.run([sys.executable, "axes.py"], cwd=user_folder, capture_output=True,
                          text=True, env=ENV, timeout=180, check=False)
    assert done.returncode == 0, done.stderr
    x, y = map(float, done.stdout.split())
    assert x > 0.5 and y < -0.5




def test_connect_your_drive_names_every_mode_the_homing_and_the_stand_ins():
    """The modes of the mode table, the homing and the keys that stand in for what a drive
    lacks are each named where a user connects a drive."""
    from hil.drivers.canopen.current_limit import MAX_TORQUE_STAND_IN
    from hil.drivers.canopen.scaling import INCREMENTS, RATED
    from hil.protocols.cia402 import OPERATION_MODES

    section = README[README.index("## Connect your drive"):]
    section = section[:section.index("\n## ", 1)]
    for mode in OPERATION_MODES:
        assert f"`{mode}`" in section or mode.upper() in section, mode
    for stand_in in (INCREMENTS, RATED, MAX_TORQUE_STAND_IN):
        assert f"`{stand_in.key}`" in section and stand_in.name in section, stand_in.key
    for command in ("hil drive home", "hil drive move", "hil servo run --home"):
        assert command in section, command
