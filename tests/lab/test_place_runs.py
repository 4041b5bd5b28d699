"""``hil bench run --place`` / ``hil servo run --place`` from a user's folder, against a real
labgrid coordinator and exporter publishing hil's emulators (tests/lab/conftest.py)."""

from __future__ import annotations

import json
import signal
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
    other_node = hil(tmp_path, "servo", "run", "--controller", "pid", "--place", "drive",
                     "--node", "2", LG_COORDINATOR=lab.address)
    assert other_node.returncode == 2
    assert other_node.stderr.strip().splitlines() == [
        "hil: error: --node and place drive's HilDrive (node = 1) both set it: give one"]
    assert lab.holder("drive") is None


def test_a_place_held_by_someone_else_is_refused_then_waited_for(lab, tmp_path):
    client(lab.address, "-p", "bench", "acquire", user="alice")
    holder = lab.holder("bench")
    assert holder.endswith("/alice")
    run = ("bench", "run", "--controller", "bc", "--cycles", "1", "--place", "bench",
           "--coordinator", lab.address, "--out", tmp_path / "b.mcap")
    refused = hil(tmp_path, *run)
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines() == [
        f"hil: error: place bench is held by {holder} (wait for it with --wait S)"]
    assert not (tmp_path / "b.mcap").exists()
    gave_up = hil(tmp_path, *run, "--wait", "1")
    assert gave_up.returncode == 2
    assert gave_up.stderr.strip().splitlines()[-1] == (
        f"hil: error: place bench is still held by {holder} after --wait 1 s")
    assert "Reservation" not in client(lab.address, "reservations").stdout

    waiting = subprocess.Popen([sys.executable, "-m", "hil", *map(str, run), "--wait", "600"],
                               cwd=tmp_path, env=user_env(), stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        lab.wait_for_reservation()
        assert waiting.poll() is None  # still waiting: alice holds the place
        client(lab.address, "-p", "bench", "release", user="alice")
        _, err = waiting.communicate(timeout=300)
    finally:
        if waiting.poll() is None:
            waiting.kill()
            waiting.communicate()
    assert waiting.returncode == 0, err
    assert f"place bench is held by {holder}: waiting up to 600 s" in err
    assert "place bench acquired after" in err
    assert run_metadata(tmp_path / "b.mcap", "run")["lab"]["acquired_by_run"] is True
    assert lab.holder("bench") is None
    assert "Reservation" not in client(lab.address, "reservations").stdout


def test_a_run_that_fails_releases_the_place_and_one_the_user_holds_stays_held(lab, tmp_path):
    unknown = hil(tmp_path, "bench", "run", "--controller", "bc", "--place", "nosuch",
                  "--coordinator", lab.address)
    assert unknown.returncode == 2
    assert unknown.stderr.strip().splitlines() == [
        f"hil: error: --place nosuch: no such place at the coordinator {lab.address} (its "
        "places: bad, bench, drive; labgrid-client -p nosuch create makes it)"]
    no_bench = hil(tmp_path, "bench", "run", "--controller", "bc", "--place", "drive",
                   "--coordinator", lab.address)
    assert no_bench.returncode == 2
    assert no_bench.stderr.strip().splitlines() == [
        "hil: error: place drive must hold one HilBench resource, it holds 0 (none): "
        "labgrid-client -p drive add-match EXPORTER/GROUP/HilBench/NAME"]
    bad = hil(tmp_path, "servo", "run", "--controller", "pid", "--place", "bad",
              "--coordinator", lab.address)
    assert bad.returncode == 2
    [line] = bad.stderr.strip().splitlines()
    assert line.startswith(f"hil: error: place bad: resource {EXPORTER}/bad-1/HilDrive/"
                           "HilDrive: 'node' must be <class 'int'>")
    assert lab.holder("drive") is None and lab.holder("bad") is None
    failed = hil(tmp_path, "bench", "run", "--controller", "nosuch.module:Nope", "--place",
                 "bench", "--coordinator", lab.address)
    assert failed.returncode == 2 and "nosuch" in failed.stderr
    assert lab.holder("bench") is None

    client(lab.address, "-p", "bench", "acquire")
    mine = lab.holder("bench")
    out = hil(tmp_path, "bench", "run", "--controller", "bc", "--cycles", "1", "--place",
              "bench", "--coordinator", lab.address, "--out", tmp_path / "b.mcap")
    assert out.returncode == 0, out.stderr
    assert run_metadata(tmp_path / "b.mcap", "run")["lab"]["acquired_by_run"] is False
    assert lab.holder("bench") == mine


@pytest.mark.parametrize("signal_, status", [(signal.SIGINT, 130), (signal.SIGKILL, -9)])
def test_an_interrupted_run_releases_the_place_a_killed_one_leaves_it_locked(
        lab, tmp_path, signal_, status):
    """Ctrl-C stops the run safely and releases the place; SIGKILL leaves it acquired, as
    labgrid does, until ``labgrid-client -p NAME release``."""
    run = subprocess.Popen(
        [sys.executable, "-m", "hil", "bench", "run", "--controller", "bc", "--cycles", "1000",
         "--place", "bench", "--coordinator", lab.address, "--out", str(tmp_path / "b.mcap")],
        cwd=tmp_path, env=user_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lab.wait_for_session(tmp_path / "b.mcap")
        mine = lab.holder("bench")
        assert mine is not None
        run.send_signal(signal_)
        _, err = run.communicate(timeout=300)
    finally:
        if run.poll() is None:
            run.kill()
            run.communicate()
    assert run.returncode == status, err
    if signal_ == signal.SIGINT:
        assert lab.holder("bench") is None
        return
    assert lab.holder("bench") == mine
    refused = hil(tmp_path, "bench", "run", "--controller", "bc", "--place", "bench",
                  "--coordinator", lab.address, LG_USERNAME="bob")
    assert refused.returncode == 2 and f"held by {mine}" in refused.stderr
    client(lab.address, "-p", "bench", "release")
    assert lab.holder("bench") is None
