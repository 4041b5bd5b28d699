"""Who may change a running machine: a live view that listens beyond loopback is read-only
unless the run was started with ``--allow-remote-tuning``.

From outside: ``hil servo run --live 0.0.0.0:PORT`` started as a user starts it, watched and
(not) tuned by an independent Foxglove WebSocket client and by ``hil tune``; a client on
another network (a network namespace joined by a veth pair, where the machine lets the test
make one) against a run that listens on every interface of its namespace; and the opt-in
through a recorder's writer process, as a run's live view serves it, with a stand-in tuner."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from hil.core.recording.live import read_only_reason
from hil.core.recording.reader import read_session
from hil.core.recording.recorder import Recorder
from hil.core.recording.recording_options import RecordingOptions
from tests.live.foxglove_client import FoxgloveClient
from tests.live.test_tune_run import ANSWER_S, CONNECT_S, INTERRUPTED, WARNING, free_port, user_env
from tests.live.test_tune_wire import StandInTuner, tune

pytestmark = [pytest.mark.slow]

READ_ONLY = "read-only unless the run is started with --allow-remote-tuning"


@pytest.mark.parametrize(("host", "read_only"), [
    ("127.0.0.1", False), ("127.0.0.2", False), ("localhost", False), ("::1", False),
    ("0.0.0.0", True), ("::", True), ("192.0.2.7", True), ("fd00::7", True)])
def test_only_a_view_that_listens_beyond_loopback_is_read_only(host: str, read_only: bool
                                                                ) -> None:
    """All of 127.0.0.0/8 is loopback: a view on 127.0.0.2 only has clients on this machine."""
    assert bool(read_only_reason(host, remote_tuning=False)) == read_only
    assert read_only_reason(host, remote_tuning=True) == ""


def start_run(cwd: Path, live: str, *, netns: str | None = None) -> subprocess.Popen[str]:
    """A long lockstep PID run serving its live view at ``live`` (in the network namespace
    ``netns``, if given); the test stops it."""
    command = [sys.executable, "-m", "hil", "servo", "run", "--controller", "pid",
               "--duration", "600", "--quiet", "--live", live, "--out", str(cwd / "run.mcap")]
    if netns is not None:
        command = ["ip", "netns", "exec", netns, *command]
    return subprocess.Popen(command, cwd=cwd, env=user_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def try_to_tune(url: str, run: subprocess.Popen[str]) -> dict[str, Any]:
    """What a client of ``url`` saw: the parameters, a set of the PID gain, its status."""
    client = FoxgloveClient(url, timeout_s=CONNECT_S, alive=run.poll)
    try:
        listed = client.get_parameters([], "list", ANSWER_S)
        client.subscribe_parameter_updates(["controller.kp"])
        kp = listed["controller.kp"]["value"]
        answer = client.set_parameters({"controller.kp": kp / 2}, "kp", ANSWER_S)
        assert client.wait_for(lambda: any(s["id"].endswith(":kp:controller.kp")
                                           for s in client.statuses), ANSWER_S)
        status = next(s for s in client.statuses if s["id"].endswith(":kp:controller.kp"))
        return {"kp": kp, "answer": answer, "status": status}
    finally:
        client.close()


def stop(run: subprocess.Popen[str]) -> str:
    """SIGINT to the run; its stderr."""
    run.send_signal(signal.SIGINT)
    _, stderr = run.communicate(timeout=120)
    assert run.returncode == INTERRUPTED, stderr
    return stderr


def assert_refused(seen: dict[str, Any]) -> None:
    assert seen["answer"] == {"controller.kp": seen["kp"]}  # the value stays
    status = seen["status"]
    assert status["level"] == WARNING
    assert "beyond loopback" in status["message"] and READ_ONLY in status["message"]


def test_a_view_for_the_network_is_read_only_and_says_why(tmp_path: Path) -> None:
    port = free_port()
    run = start_run(tmp_path, f"0.0.0.0:{port}")
    try:
        seen = try_to_tune(f"ws://127.0.0.1:{port}", run)
        by_hil_tune = tune(tmp_path, f"127.0.0.1:{port}", "safety.following_error_deg=30")
    except BaseException:
        run.kill()
        raise
    stderr = stop(run)
    assert_refused(seen)
    assert by_hil_tune.returncode == 1
    assert by_hil_tune.stderr.startswith("safety.following_error_deg = 30 refused: this live "
                                         "view listens beyond loopback (0.0.0.0)")
    assert READ_ONLY in by_hil_tune.stderr
    warnings = [line for line in stderr.splitlines() if line.startswith("hil: warning:")]
    assert warnings == [
        f"hil: warning: the live view on ws://0.0.0.0:{port} listens beyond loopback: any "
        "machine that reaches this one may watch it, not set the run's parameters "
        "(--allow-remote-tuning would let them) (a 127.0.0.1 address keeps it to this machine)"]
    session = read_session(tmp_path / "run.mcap")
    assert not [m for _, m in session.topic("/events") if m["kind"] == "param.changed"]


@pytest.fixture
def netns(tmp_path: Path) -> Iterator[tuple[str, str]]:
    """A network namespace joined to this one by a veth pair: (its name, its address). The
    pair goes with the namespace."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("a network namespace needs root and iproute2's ip")
    pid = os.getpid()
    name, outer, inner = f"hil-live-{pid}", f"hl{pid}a", f"hl{pid}b"
    subnet = f"10.231.{pid % 250}.{4 * (pid // 250 % 60)}"  # a /30 of its own
    near, far = subnet.rsplit(".", 1)[0], int(subnet.rsplit(".", 1)[1])
    commands = [["ip", "netns", "add", name],
                ["ip", "link", "add", outer, "type", "veth", "peer", "name", inner],
                ["ip", "link", "set", inner, "netns", name],
                ["ip", "addr", "add", f"{near}.{far + 1}/30", "dev", outer],
                ["ip", "link", "set", outer, "up"],
                ["ip", "netns", "exec", name, "ip", "addr", "add", f"{near}.{far + 2}/30",
                 "dev", inner],
                ["ip", "netns", "exec", name, "ip", "link", "set", inner, "up"],
                ["ip", "netns", "exec", name, "ip", "link", "set", "lo", "up"]]
    try:
        for command in commands:
            made = subprocess.run(command, capture_output=True, text=True, timeout=30)
            if made.returncode != 0:
                pytest.skip(f"cannot make a network namespace here: {made.stderr.strip()}")
        yield name, f"{near}.{far + 2}"
    finally:
        subprocess.run(["ip", "netns", "del", name], capture_output=True, timeout=30)


def test_a_client_on_another_network_cannot_tune_a_view_for_the_network(
        tmp_path: Path, netns: tuple[str, str]) -> None:
    """The run listens on every interface of its namespace; this test's client reaches it
    over the veth pair, from an address that is not loopback."""
    name, address = netns
    port = free_port()
    run = start_run(tmp_path, f"0.0.0.0:{port}", netns=name)
    try:
        seen = try_to_tune(f"ws://{address}:{port}", run)
    except BaseException:
        run.kill()
        raise
    stop(run)
    assert_refused(seen)


def test_allow_remote_tuning_lets_the_clients_of_a_view_for_the_network_set(
        tmp_path: Path) -> None:
    port = free_port()
    recorder = Recorder(tmp_path / "s.mcap", tunable=True, options=RecordingOptions(
        live=f"0.0.0.0:{port}", live_remote_tuning=True))
    try:
        recorder.wait_ready()
        tuner = StandInTuner()
        recorder.serve_parameters(tuner)
        client = FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=CONNECT_S)
        try:
            assert client.set_parameters({"controller.kp": 3.5}, "kp", ANSWER_S) == {
                "controller.kp": 3.5}
        finally:
            client.close()
    finally:
        recorder.close()
    assert tuner.requests[-1][:2] == ("controller.kp", 3.5)
