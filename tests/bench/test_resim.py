"""``hil resim`` of a bench session, from the command line: one lockstep cycle re-simulated with
its own controller comes back tick for tick, the emulator's ``[faults]`` schedule played at the
same session time; a load made a model file (``--model LOAD=F.json``) changes the plant."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from importlib import resources
from pathlib import Path

import pytest

from hil.core.recording.reader import SessionData, read_session
from tests.cli import hil_here, hil_in

pytestmark = [pytest.mark.slow]  # processes, emulators, sessions

FAULT = "load_step@5-6:va=100"
TOPICS = ("/bench/power", "/bench/relays", "/bench/levels")
PACKAGED_MODELS = Path(str(resources.files("hil.configs"))) / "models"


def hil(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``hil ARGS`` in a process of its own, from a folder outside the repository."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=180)


def faults(data: SessionData) -> list[tuple[int, str]]:
    return [(t, m["data"]["fault"]) for t, m in data.topic("/events")
            if m["kind"] == "fault.injected"]


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A BC run of one 10 s cycle of a bench whose emulator steps a load in at 5 s."""
    folder = tmp_path_factory.mktemp("resim")
    (folder / "bench.toml").write_text(f"""[plant]\nseed = 7\n\n[faults]\nschedule = ["{FAULT}"]

[sequence]
period_s = 10.0
stages = [{{ start_s = 0.0, end_s = 4.0, on = [] }},
          {{ start_s = 4.0, end_s = 10.0, on = ["M1", "M2"] }}]
""")
    # in this process: each start costs a second
    assert hil_in(folder, "bench", "run", "--controller", "bc", "--cycles", "1", "--config",
                  "bench.toml", "--quiet", "--out", "recorded.mcap") == 0
    return folder


def test_a_bench_cycle_comes_back_tick_for_tick_with_its_faults(folder):
    done = hil(folder, "resim", "recorded.mcap", "--json", "--out", "same.mcap")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["resim"]["plant"] == "the recorded emulator"
    recorded, resim = read_session(folder / "recorded.mcap"), read_session(folder / "same.mcap")
    for topic in TOPICS:
        assert resim.topic(topic) == recorded.topic(topic), topic
    assert len(resim.topic("/bench/power")) == 1000  # one 10 s cycle at 10 ms
    assert faults(resim) == faults(recorded)
    assert faults(resim)[0][1] == f"{FAULT}.0" and faults(resim)[0][0] == 5_010_000_000
    assert resim.metadata["resim"]["controller"] == "bc"


def test_a_load_model_file_changes_the_plant(folder, capsys):
    model = PACKAGED_MODELS / "P1.json"
    done = hil_here(capsys, "resim", "recorded.mcap", "--model", f"P1={model}", "--out",
                    "model.mcap", cwd=folder)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[0] == (
        "resim of recorded.mcap (recorded on hil's emulator): controller bc against the "
        f"emulator with the load models P1={model}")
    resim = read_session(folder / "model.mcap")
    tables = json.loads(resim.metadata["config"]["json"])["bench"]
    assert tables["plant"]["loads"]["P1"]["model"] == str(model)
    assert resim.topic("/bench/power") != read_session(folder / "recorded.mcap"
                                                       ).topic("/bench/power")
