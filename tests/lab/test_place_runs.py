"""``hil bench run --place`` / ``hil servo run --place`` from a user's folder, against a real
labgrid coordinator and exporter publishing hil's emulators (tests/lab/conftest.py). The runs
that hold a place go through ``python -m hil``; the refusals, variants of them, run in this
process (:func:`tests.cli.hil_here`)."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys

import pytest

from hil.core.recording.reader import read_session
from tests.cli import hil_here
from tests.lab.conftest import EXPORTER, client, user_env

pytestmark = [pytest.mark.lab, pytest.mark.slow]


def hil(folder, *args, **env):
    """``python -m hil ARGS`` from ``folder`` (``env``: more variables, LG_USERNAME...)."""
    return subprocess.run([sys.executable, "-m", "hil", *map(str, args)], cwd=folder,
                          env=user_env(**env), capture_output=True, text=True, timeout=300)


def refused(capsys, folder, *args, user=None):
    """``hil ARGS`` in this process (as labgrid user ``user``): exit status 2, its one line."""
    with pytest.MonkeyPatch.context() as patch:
        patch.delenv("LG_COORDINATOR", raising=False)
        if user is not None:
            patch.setenv("LG_USERNAME", user)
        out = hil_here(capsys, *args, cwd=folder)
    assert out.returncode == 2, out.stdout + out.stderr
    [line] = out.stderr.strip().splitlines()
    return line


def run_metadata(session, kind):
    """The session's run options as its metadata records them (``run`` / ``servo``)."""
    return json.loads(read_session(str(session)).metadata["config"]["json"])[kind]


def test_the_exporter_publishes_the_emulated_bench_and_drive(lab):
    out = client(lab.address, "-v", "resources").stdout
    assert f"{EXPORTER}/bench-1/HilBench" in out and f"{EXPORTER}/drive-1/HilDrive" in out
    assert lab.bench_url in out and lab.drive_url in out


def test_a_bench_run_on_a_place_holds_it_for_the_run_and_records_it(lab, tmp_path):
    place = lab.place("bench-1")
    out = hil(tmp_path, "bench", "run", "--controller", "bc", "--cycles", "1", "--place",
              place, "--coordinator", lab.address, "--out", tmp_path / "b.mcap", "--json")
    assert out.returncode == 0, out.stderr
    run = run_metadata(tmp_path / "b.mcap", "run")
    assert run["bench"] == lab.bench_url and run["config_path"] == str(lab.bench_config)
    lab_info = run["lab"]
    assert lab_info["place"] == place and lab_info["acquired_by_run"] is True
    [resource] = lab_info["resources"]
    assert resource["cls"] == "HilBench" and resource["exporter"] == EXPORTER
    assert resource["url"] == lab.bench_url and resource["host"]
    assert lab.holder(place) is None


def test_a_servo_run_on_a_place_takes_the_drive_and_its_node(lab, tmp_path, capsys):
    place = lab.place("drive-1")
    out = hil(tmp_path, "servo", "run", "--controller", "pid", "--duration", "0.2", "--place",
              place, "--out", tmp_path / "s.mcap", "--json", LG_COORDINATOR=lab.address)
    assert out.returncode == 0, out.stderr
    run = run_metadata(tmp_path / "s.mcap", "servo")
    assert run["drive"] == lab.drive_url and run["node"] == 1
    assert run["lab"]["resources"][0]["cls"] == "HilDrive"
    assert lab.holder(place) is None
    assert refused(capsys, tmp_path, "servo", "run", "--controller", "pid", "--place", place,
                   "--coordinator", lab.address, "--node", "2") == (
        f"hil: error: --node and place {place}'s HilDrive (node = 1) both set it: give one")
    assert lab.holder(place) is None


def test_a_place_held_by_someone_else_is_refused_then_waited_for(lab, tmp_path, capsys):
    place = lab.place("bench-1")
    lab.acquire(place, user="alice")
    holder = lab.holder(place)
    assert holder.endswith("/alice")
    run = ("bench", "run", "--controller", "bc", "--cycles", "1", "--place", place,
           "--coordinator", lab.address, "--out", tmp_path / "b.mcap")
    assert refused(capsys, tmp_path, *run) == (
        f"hil: error: place {place} is held by {holder} (wait for it with --wait S)")
    assert not (tmp_path / "b.mcap").exists()
    with pytest.MonkeyPatch.context() as patch:
        patch.delenv("LG_COORDINATOR", raising=False)
        gave_up = hil_here(capsys, *run, "--wait", "1", cwd=tmp_path)
    assert gave_up.returncode == 2
    assert gave_up.stderr.strip().splitlines()[-1] == (
        f"hil: error: place {place} is still held by {holder} after --wait 1 s")
    assert lab.reservations() == []

    waiting = subprocess.Popen([sys.executable, "-m", "hil", *map(str, run), "--wait", "600"],
                               cwd=tmp_path, env=user_env(), stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        lab.wait_for_reservation()
        assert waiting.poll() is None  # still waiting: alice holds the place
        lab.release(place)
        _, err = waiting.communicate(timeout=300)
    finally:
        if waiting.poll() is None:
            waiting.kill()
            waiting.communicate()
    assert waiting.returncode == 0, err
    assert f"place {place} is held by {holder}: waiting up to 600 s" in err
    assert f"place {place} acquired after" in err
    assert run_metadata(tmp_path / "b.mcap", "run")["lab"]["acquired_by_run"] is True
    assert lab.holder(place) is None
    assert lab.reservations() == []


def test_a_run_that_fails_releases_the_place_and_one_the_user_holds_stays_held(
        lab, tmp_path, capsys):
    bench, drive, bad = lab.place("bench-1"), lab.place("drive-1"), lab.place("bad-1")
    unknown = refused(capsys, tmp_path, "bench", "run", "--controller", "bc", "--place",
                      "nosuch", "--coordinator", lab.address)
    assert re.fullmatch(
        rf"hil: error: --place nosuch: no such place at the coordinator {lab.address} \(its "
        rf"places: .*\b{bench}\b.*; labgrid-client -p nosuch create makes it\)", unknown)
    assert refused(capsys, tmp_path, "bench", "run", "--controller", "bc", "--place", drive,
                   "--coordinator", lab.address) == (
        f"hil: error: place {drive} must hold one HilBench resource, it holds 0 (none): "
        f"labgrid-client -p {drive} add-match EXPORTER/GROUP/HilBench/NAME")
    assert refused(capsys, tmp_path, "servo", "run", "--controller", "pid", "--place", bad,
                   "--coordinator", lab.address).startswith(
        f"hil: error: place {bad}: resource {EXPORTER}/bad-1/HilDrive/HilDrive: 'node' must "
        "be <class 'int'>")
    assert lab.holder(drive) is None and lab.holder(bad) is None
    assert "nosuch" in refused(capsys, tmp_path, "bench", "run", "--controller",
                               "nosuch.module:Nope", "--place", bench, "--coordinator",
                               lab.address)
    assert lab.holder(bench) is None

    lab.acquire(bench)
    mine = lab.holder(bench)
    out = hil(tmp_path, "bench", "run", "--controller", "bc", "--cycles", "1", "--place",
              bench, "--coordinator", lab.address, "--out", tmp_path / "b.mcap")
    assert out.returncode == 0, out.stderr
    assert run_metadata(tmp_path / "b.mcap", "run")["lab"]["acquired_by_run"] is False
    assert lab.holder(bench) == mine


@pytest.mark.parametrize("signal_, status", [(signal.SIGINT, 130), (signal.SIGKILL, -9)])
def test_an_interrupted_run_releases_the_place_a_killed_one_leaves_it_locked(
        lab, tmp_path, capsys, signal_, status):
    """Ctrl-C stops the run safely and releases the place; SIGKILL leaves it acquired, as
    labgrid does, until ``labgrid-client -p NAME release``."""
    place = lab.place("bench-1")
    run = subprocess.Popen(
        [sys.executable, "-m", "hil", "bench", "run", "--controller", "bc", "--cycles", "1000",
         "--place", place, "--coordinator", lab.address, "--out", str(tmp_path / "b.mcap")],
        cwd=tmp_path, env=user_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lab.wait_for_session(tmp_path / "b.mcap", run)
        mine = lab.holder(place)
        assert mine is not None
        run.send_signal(signal_)
        _, err = run.communicate(timeout=300)
    finally:
        if run.poll() is None:
            run.kill()
            run.communicate()
    assert run.returncode == status, err
    if signal_ == signal.SIGINT:
        assert lab.holder(place) is None
        return
    assert lab.holder(place) == mine
    assert refused(capsys, tmp_path, "bench", "run", "--controller", "bc", "--place", place,
                   "--coordinator", lab.address, user="bob") == (
        f"hil: error: place {place} is held by {mine} (wait for it with --wait S)")
    client(lab.address, "-p", place, "release")
    assert lab.holder(place) is None


def test_servo_identify_on_a_place_holds_it_and_records_it(lab, tmp_path):
    place = lab.place("drive-1")
    out = hil(tmp_path, "servo", "identify", "--duration", "0.5", "--place", place,
              "--coordinator", lab.address, "--out", tmp_path / "i.mcap", "--json")
    assert out.returncode == 0, out.stderr
    run = run_metadata(tmp_path / "i.mcap", "servo")
    assert run["drive"] == lab.drive_url and run["node"] == 1
    assert run["controller"] == "hil.servo.identify:excitation"
    assert run["lab"]["place"] == place and run["lab"]["acquired_by_run"] is True
    assert lab.holder(place) is None


def test_a_sweep_on_a_place_may_not_sweep_its_drive(lab, tmp_path, capsys):
    place = lab.place("drive-1")
    assert refused(capsys, tmp_path, "sweep", "servo", "--controller", "pid", "--serial",
                   "--grid", "drive=emulated", "--place", place, "--coordinator",
                   lab.address) == (f"hil: error: --place {place} and a swept drive both say "
                                    "where the drive is: give one")
    assert lab.holder(place) is None
