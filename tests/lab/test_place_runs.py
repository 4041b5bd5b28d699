"""``hil bench run --place`` / ``hil servo run --place`` from a user's folder, against a real
labgrid coordinator and exporter publishing hil's emulators (tests/lab/conftest.py)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from hil.core.recording.reader import read_session
from tests.lab.conftest import EXPORTER, client, user_env

pytestmark = [pytest.mark.lab, pytest.mark.slow]


def hil(folder, *args, **env):
    """``python -m hil ARGS`` from ``folder`` (``env``: more variables, LG_USERNAME...)."""
    return subprocess.run([sys.executable, "-m", "hil", *map(str, args)], cwd=folder,
                          env=user_env(**env), capture_output=True, text=True, timeout=300)


def run_metadata(session, kind):
    """The session's run options as its metadata records them (``run`` / ``servo``)."""
    return json.loads(read_session(str(session)).metadata["config"]["json"])[kind]


def test_the_exporter_publishes_the_emulated_bench_and_drive(lab):
    out = client(lab.address, "-v", "resources").stdout
    assert f"{EXPORTER}/bench-1/HilBench" in out and f"{EXPORTER}/drive-1/HilDrive" in out
    assert lab.bench_url in out and lab.drive_url in out


def test_a_bench_run_on_a_place_holds_it_for_the_run_and_records_it(lab, tmp_path):
    out = hil(tmp_path, "bench", "run", "--controller", "bc", "--cycles", "1", "--place",
              "bench", "--coordinator", lab.address, "--out", tmp_path / "b.mcap", "--json")
    assert out.returncode == 0, out.stderr
    run = run_metadata(tmp_path / "b.mcap", "run")
    assert run["bench"] == lab.bench_url
    lab_info = run["lab"]
    assert lab_info["place"] == "bench" and lab_info["acquired_by_run"] is True
    [resource] = lab_info["resources"]
    assert resource["cls"] == "HilBench" and resource["exporter"] == EXPORTER
    assert resource["url"] == lab.bench_url and resource["host"]
    assert lab.holder("bench") is None


def test_a_servo_run_on_a_place_takes_the_drive_and_its_node(lab, tmp_path):
    out = hil(tmp_path, "servo", "run", "--controller", "pid", "--duration", "0.2", "--place",
              "drive", "--out", tmp_path / "s.mcap", "--json", LG_COORDINATOR=lab.address)
    assert out.returncode == 0, out.stderr
    run = run_metadata(tmp_path / "s.mcap", "servo")
    assert run["drive"] == lab.drive_url and run["node"] == 1
    assert run["lab"]["resources"][0]["cls"] == "HilDrive"
    assert lab.holder("drive") is None
