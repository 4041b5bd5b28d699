"""What emulator-backed tests promise holds on a busy machine: both cores kept busy by
processes niced as a CI neighbour is (tests/busy.py) while a user's tests and lockstep runs go
on. A lockstep session under load is its quiet twin, bit for bit; a paused emulator under load
changes nothing; the pytest guide's fixture example passes every time."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hil import api
from hil.servo.run import ServoRunOptions, run_servo
from tests.busy import busy_machine, busy_now
from tests.docs import block
from tests.session_digest import EXPERIMENTS, kpi_digest, session_digest

pytestmark = [pytest.mark.slow]

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
# two rounds: each test of the example after one of its kind in the same session (a fixture's
# emulator gone, the next one started) with both cores busy; each round costs the two spinning
# cores its whole length (ten of ten pass by hand too: ROUNDS = 10)
ROUNDS = 2


def rounds_of(example: str) -> str:
    """The guide's example, its tests run :data:`ROUNDS` times each."""
    body = example.replace("\ndef test_", "\n@pytest.mark.parametrize('round', range("
                           f"{ROUNDS}))\ndef test_").replace("(hil_bench)", "(round, hil_bench)")
    return "import pytest\n" + body.replace("(hil_drive)", "(round, hil_drive)")


def first_test_started(pytest_run: subprocess.Popen[str], bound_s: float = 120.0) -> None:
    """Wait until ``pytest_run`` has started a process of its own (its first test's emulator;
    pytest's own start-up is not what is checked under load), or has ended, or ``bound_s``."""
    deadline = time.monotonic() + bound_s
    while pytest_run.poll() is None and time.monotonic() < deadline:
        for children in Path(f"/proc/{pytest_run.pid}/task").glob("*/children"):
            with contextlib.suppress(OSError):
                if children.read_text().strip():
                    return
        time.sleep(0.02)


def test_the_guides_fixture_example_passes_round_after_round_under_load(tmp_path):
    """The pytest guide's `hil_bench` / `hil_drive` example, as a user copies it, :data:`ROUNDS`
    times over, both cores busy all along from its first test on (its only run in the suite:
    tests/test_doc_examples.py leaves it here)."""
    folder = tmp_path / "my_lab"
    folder.mkdir()
    shutil.copy(EXAMPLES / "my_controllers.py", folder / "my_controllers.py")
    example = block("guides/pytest.md", "python",
                    "def test_threshold_relays_keep_the_levels_in_range")
    assert "def test_threshold_relays_keep_the_levels_in_range(hil_bench)" in example
    (folder / "test_guide_example.py").write_text(rounds_of(example))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # a user's shell
    with subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "--rootdir", str(folder), "test_guide_example.py"], cwd=folder,
                          env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          stdin=subprocess.DEVNULL, text=True) as run:
        first_test_started(run)
        with busy_machine() as spinning:
            stdout, stderr = run.communicate(timeout=600)
            loaded = busy_now(spinning)
    assert loaded, "the machine was not kept busy all along"
    assert run.returncode == 0, stdout[-3000:] + stderr[-2000:]
    assert f"{2 * ROUNDS} passed" in stdout


def experiment(name: str, out: Path, **extra: object) -> dict:
    function, arguments = EXPERIMENTS[name]
    return getattr(api, function)(**arguments, **extra, out=str(out))


@pytest.mark.parametrize("name", ["servo-mpc", "bench-bc"])
def test_a_lockstep_session_under_load_is_its_quiet_twin(tmp_path, name):
    quiet = experiment(name, tmp_path / "quiet.mcap")
    with busy_machine() as spinning:
        loaded = experiment(name, tmp_path / "loaded.mcap")
        assert busy_now(spinning)
    assert session_digest(quiet["mcap"]) == session_digest(loaded["mcap"])
    assert kpi_digest(quiet) == kpi_digest(loaded)


def test_a_lockstep_run_over_the_wire_under_load_with_its_emulator_paused_is_its_twin(tmp_path):
    """Under load, over socketcand, the emulator process stopped for 1 s mid-run: the session
    is the one the emulator in process records on a quiet machine."""
    name = "servo-pid"
    quiet = experiment(name, tmp_path / "quiet.mcap")
    _, arguments = EXPERIMENTS[name]
    options = {key: value for key, value in arguments.items() if key != "limits"}
    # the emulator started before the machine is loaded: the run under load is what is checked
    with api.start_drive_emulator() as drive, busy_machine() as spinning:
        def pause() -> None:
            time.sleep(0.1)
            os.kill(drive.pid, signal.SIGSTOP)
            time.sleep(1.0)
            os.kill(drive.pid, signal.SIGCONT)

        threads: list[threading.Thread] = []

        def paused(_master: object) -> None:
            threads.append(threading.Thread(target=pause, daemon=True))
            threads[0].start()

        loaded = run_servo(ServoRunOptions(**options, limits=(), drive=drive.url,
                                           out=str(tmp_path / "wire.mcap")), on_started=paused)
        threads[0].join()
        assert busy_now(spinning)
    assert loaded.stop_reason == "completed"
    for topic in ("/drive/command", "/drive/feedback", "/drive/stop"):
        assert session_digest(quiet["mcap"])[topic] == session_digest(loaded.session_path)[topic]
