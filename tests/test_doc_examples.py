"""The documentation's code (the README and the site's pages, tests/docs.py), run as a user
would, from a folder outside the repository: its Python blocks (the controllers file, the API
tour and the several axes, run as scripts in this process; the README's tour and first test;
the pytest guide's example runs five times over on a busy machine in
tests/integration/test_busy_machine.py), its `hil` commands checked against
the parser (every flag it shows exists) and the limit examples run for the exit status the
pages promise (the first from a ``hil`` process, the others from the command line run in this
process). A page that drifts from the code fails here."""

import os
import runpy
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from hil.cli.main import build_parser, main
from tests.cli import NOT_A_USERS_PLUGINS
from tests.docs import block, blocks, page, pages, section

pytestmark = [pytest.mark.timeout(240), pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT))
#: the page of the controllers file, the limits and the API tour
CONTROLLERS, LIMITS, API = "guides/controller.md", "guides/limits.md", "guides/python-api.md"


def hil_commands(text=None):
    """Every `hil ...` command of the sh blocks of ``text`` (None: of every page and the
    README), continuation lines joined."""
    commands = []
    for code in blocks(text, "sh") if text is not None else \
            [code for each in pages().values() for code in blocks(each, "sh")]:
        for line in code.replace("\\\n", " ").splitlines():
            line = " ".join(line.split("  #")[0].split())
            if line.startswith("hil "):
                commands.append(line)
    return commands


@pytest.fixture
def user_folder(tmp_path):
    """A folder of the user's: the guide's controllers file in it, nothing of the repo."""
    (tmp_path / "my_controllers.py").write_text(
        block(CONTROLLERS, "python", "class ThresholdRelays:"))
    return tmp_path


def test_every_hil_command_of_the_docs_parses():
    commands = hil_commands()
    assert len(commands) >= 60
    parser = build_parser()
    for command in commands:
        argv = shlex.split(command)[1:]
        if "--help" in argv:
            continue  # prints and exits 0 by design
        try:
            parser.parse_args(argv)
        except SystemExit:
            pytest.fail(f"command of the docs does not parse: {command}")


@pytest.mark.parametrize(("command", "status", "outside"), [
    ("hil servo run --controller pid --limit 'rms_error_deg<=0.5' --limit "
     "'abs_command_mA<=1000' --junit servo.xml", 0, True),
    ("hil servo run --controller pid --limit 'max_error_deg<=0.1'", 1, False),
    ("hil servo run --controller my_controllers.py:PdPosition --param kp=400 "
     "--reference sine:amplitude=2,frequency=1 --duration 2", 0, False),
])
def test_the_docs_commands_give_the_status_they_say(user_folder, monkeypatch, capfd, command,
                                                    status, outside):
    assert command in hil_commands(page(LIMITS)) + hil_commands(page(CONTROLLERS))
    argv = shlex.split(command)[1:]
    if outside:
        done = subprocess.run([sys.executable, "-m", "hil", *argv], cwd=user_folder,
                              capture_output=True, text=True, env=ENV, timeout=120,
                              check=False)
        assert done.returncode == status, done.stderr
    else:
        monkeypatch.chdir(user_folder)
        assert main(argv) == status, capfd.readouterr().err


def run_here(folder, script, text, monkeypatch, capfd):
    """A user's ``script`` (``text``) run from ``folder`` in this process, as ``python
    SCRIPT`` would (the Python API is what it tries, not a process start): what it printed.
    Its own modules are forgotten after, so another folder's file of the same name loads."""
    (folder / script).write_text(text)
    monkeypatch.chdir(folder)
    monkeypatch.syspath_prepend(str(folder))
    before = set(sys.modules)
    capfd.readouterr()
    try:
        runpy.run_path(script, run_name="__main__")
    finally:
        for name in set(sys.modules) - before:
            if str(getattr(sys.modules[name], "__file__", "")).startswith(str(folder)):
                del sys.modules[name]
    return capfd.readouterr().out


def test_the_api_tour_runs(user_folder, monkeypatch, capfd):
    script = "from my_controllers import PdPosition, ThresholdRelays\n" + \
        block(API, "python", "kpis = api.run_bench(ThresholdRelays")
    printed = run_here(user_folder, "tour.py", script, monkeypatch, capfd)
    rms, passed, mcap = printed.splitlines()[0].split()
    assert float(rms) < 0.5 and passed == "True" and Path(user_folder, mcap).exists()


def test_the_several_axes_example_moves_each_axis_its_own_way(user_folder, monkeypatch, capfd):
    printed = run_here(user_folder, "axes.py", block("guides/drive.md", "python",
                                                     "CanDriveMaster"), monkeypatch, capfd)
    x, y = map(float, printed.split())
    assert x > 0.5 and y < -0.5


def test_connect_your_drive_names_every_mode_the_homing_and_the_stand_ins():
    """The modes of the mode table, the homing and the keys that stand in for what a drive
    lacks are each named where a user connects a drive."""
    from hil.drivers.canopen.current_limit import MAX_TORQUE_STAND_IN
    from hil.drivers.canopen.scaling import INCREMENTS, RATED
    from hil.protocols.cia402 import OPERATION_MODES

    text = section("guides/drive.md", "Connect your drive")
    for mode in OPERATION_MODES:
        assert f"`{mode}`" in text or mode.upper() in text, mode
    for stand_in in (INCREMENTS, RATED, MAX_TORQUE_STAND_IN):
        assert f"`{stand_in.key}`" in text and stand_in.name in text, stand_in.key
    for command in ("hil drive home", "hil drive move", "hil servo run --home"):
        assert command in text, command


def test_the_readme_tour_runs_the_users_controller_and_first_test(tmp_path, monkeypatch, capfd):
    """The README's five-minute tour from a user's folder: its controller file and the command
    that runs it, and its first pytest test (the getting-started page shows the same test)."""
    readme = page("README.md")
    (tmp_path / "my_controllers.py").write_text(block("README.md", "python", "class PdPosition"))
    [command] = [c for c in hil_commands(readme) if "my_controllers.py:PdPosition" in c]
    monkeypatch.chdir(tmp_path)
    assert main(shlex.split(command)[1:]) == 0, capfd.readouterr().err
    first_test = block("README.md", "python", "def test_the_pid_tracks_a_sine(hil_drive)")
    assert first_test in blocks(page("getting-started.md"), "python")
    (tmp_path / "test_first.py").write_text(first_test)
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           *NOT_A_USERS_PLUGINS, "--rootdir", str(tmp_path), "test_first.py"],
                          cwd=tmp_path,
                          capture_output=True, text=True, env=ENV, timeout=180, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "1 passed" in done.stdout

