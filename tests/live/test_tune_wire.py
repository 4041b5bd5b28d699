"""The live view's parameters, end to end short of a run: a recorder's writer process serves
them, the reverse channel carries each request back to a tuner in this (the loop's) process,
and an independent WebSocket client and ``hil tune`` (a process, outside the repository) set
them. The tuner here is a small stand-in with the run's tuner's interface."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import pytest

from hil.cli.layout import layout_path
from hil.core.recording.live import LiveSink
from hil.core.recording.recorder import Recorder
from hil.core.recording.recording_options import RecordingOptions
from hil.core.recording.tune_wire import PortServer, RemotePort
from tests.cli import hil_here
from tests.live.foxglove_client import FoxgloveClient

pytestmark = [pytest.mark.slow]

CONNECT_S = 60.0  # a process start on this shared 2-core machine can take 10 s and more
WARNING = 1       # the Foxglove protocol's status level


@dataclass(frozen=True)
class Spec:
    name: str
    value: float | int | bool | str
    unit: str
    minimum: float | None
    maximum: float | None
    step: float | None
    rebuild: bool
    stricter: str | None
    description: str


@dataclass(frozen=True)
class Result:
    name: str
    accepted: bool
    value: float | int | bool | str
    reason: str
    tick: int | None


class StandInTuner:
    """The run's tuner's interface: type, range and safety direction checked, changes counted
    as ticks, every request kept (name, value, client)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._specs: dict[str, Spec] = {}
        self.reset()
        self.requests: list[tuple[str, object, str]] = []
        self.tick = 0

    def reset(self) -> None:
        """Every parameter back to its first value."""
        with self._lock:
            self._specs = {s.name: s for s in [
                Spec("controller.kp", 2.0, "mA/deg", 0.0, 500.0, None, False, None, "gain"),
                Spec("controller.hp", 10, "ticks", 2, 40, 1, True, None, "horizon"),
                Spec("safety.max_following_error_deg", 20.0, "deg", 0.0, None, None, False,
                     "lower", "trip")]}

    def specs(self) -> list[Spec]:
        with self._lock:
            return list(self._specs.values())

    def request(self, name: str, value: object, client: str, timeout_s: float = 5.0) -> Result:
        with self._lock:
            self.requests.append((name, value, client))
            spec = self._specs[name]
            if isinstance(spec.value, float) and isinstance(value, int):
                value = float(value)  # as the run's tuner takes a whole number for a decimal
            if spec.stricter == "lower" and isinstance(value, float) and value > spec.value:
                return Result(name, False, spec.value, f"{name} may only be lowered while it "
                              f"runs ({spec.value} {spec.unit} now)", None)
            if spec.maximum is not None and isinstance(value, (int, float)) and \
                    value > spec.maximum:
                return Result(name, False, spec.value,
                              f"{value} {spec.unit} is above {spec.maximum} {spec.unit}", None)
            self.tick += 1
            self._specs[name] = replace(spec, value=value)
            return Result(name, True, value, "", self.tick)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@pytest.fixture(scope="module")
def live_session(tmp_path_factory: pytest.TempPathFactory
                 ) -> Iterator[tuple[int, StandInTuner]]:
    """A recorder with a live view whose parameters are the stand-in tuner's."""
    port = free_port()
    recorder = Recorder(tmp_path_factory.mktemp("tune") / "s.mcap",
                        options=RecordingOptions(live=str(port)), tunable=True)
    recorder.wait_ready()
    tuner = StandInTuner()
    recorder.serve_parameters(tuner)
    yield port, tuner
    recorder.close()


@pytest.fixture(autouse=True)
def first_values(live_session: tuple[int, StandInTuner]) -> None:
    """Each test starts from the tuner's first values, whatever the module's tests before it
    set: xdist's work stealing can run them out of the file's order."""
    live_session[1].reset()


@pytest.fixture(scope="module")
def client(live_session: tuple[int, StandInTuner]) -> Iterator[FoxgloveClient]:
    port, _ = live_session
    connection = FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=CONNECT_S)
    assert connection.wait_for(lambda: bool(connection.server_info), 10)
    yield connection
    connection.close()


def tune(cwd: Path, *args: object) -> subprocess.CompletedProcess[str]:
    """``hil tune ARGS`` as a user runs it: from a folder of theirs, the repository not on
    the path."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run([sys.executable, "-m", "hil", "tune", *map(str, args)], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=120)


def test_the_live_view_lists_the_parameters_with_their_values(
        client: FoxgloveClient) -> None:
    assert {"parameters", "parametersSubscribe"} <= set(client.server_info["capabilities"])
    every = client.get_parameters([], "list-all")
    assert set(every) == {"controller.kp", "controller.hp", "safety.max_following_error_deg"}
    assert every["controller.hp"]["value"] == 10 and "type" not in every["controller.hp"]
    # a float stays a float on the wire, so the panel edits it as one
    assert every["controller.kp"]["type"] == "float64"
    assert set(client.get_parameters(["controller.hp"], "list-one")) == {"controller.hp"}


def test_an_accepted_set_reaches_the_tuner_and_every_subscribed_client(
        live_session: tuple[int, StandInTuner], client: FoxgloveClient) -> None:
    port, tuner = live_session
    watcher = FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=CONNECT_S)
    try:
        watcher.subscribe_parameter_updates(["controller.kp"])
        assert watcher.wait_for(lambda: bool(watcher.server_info), 10)
        watcher.get_parameters(["controller.kp"], "sync")  # the subscription is in place
        # JSON has one number type: the tuner takes 300 for a decimal parameter as 300.0
        assert client.set_parameters({"controller.kp": 300}, "set-kp") == {
            "controller.kp": 300.0}
        assert watcher.wait_for(lambda: {"name": "controller.kp", "type": "float64",
                                         "value": 300.0} in watcher.updates, 10)
    finally:
        watcher.close()
    name, value, who = tuner.requests[-1]
    assert (name, value) == ("controller.kp", 300)  # as sent: the tuner checks its type
    assert who.startswith("live client ")
    assert client.get_parameters(["controller.kp"], "after")["controller.kp"]["value"] == 300.0


@pytest.mark.parametrize(("name", "value", "stays", "reason"), [
    ("controller.hp", 99, 10, "99 ticks is above 40 ticks"),
    ("safety.max_following_error_deg", 45.0, 20.0, "may only be lowered"),
])
def test_a_refused_set_answers_the_value_that_stays_and_a_warning_status(
        client: FoxgloveClient, name: str, value: object, stays: object, reason: str) -> None:
    request_id = f"refused-{name}"
    assert client.set_parameters({name: value}, request_id) == {name: stays}
    assert client.wait_for(lambda: any(s["id"].endswith(f":{request_id}:{name}")
                                       for s in client.statuses), 10)
    status = next(s for s in client.statuses if s["id"].endswith(f":{request_id}:{name}"))
    assert status["level"] == WARNING and reason in status["message"]
    assert name in status["message"] and "live client " in status["message"]
    assert client.get_parameters([name], f"check-{name}")[name]["value"] == stays


def test_hil_tune_sets_lists_and_says_why_a_set_was_refused(
        live_session: tuple[int, StandInTuner], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    port, tuner = live_session
    accepted = tune(tmp_path, f"127.0.0.1:{port}", "controller.hp=12")
    assert (accepted.returncode, accepted.stdout, accepted.stderr) == (
        0, "controller.hp = 12\n", "")
    assert tuner.requests[-1][:2] == ("controller.hp", 12)
    both = tune(tmp_path, f"127.0.0.1:{port}", "controller.kp=250.5", "controller.kp=9000",
                "--list", "--json")
    assert both.returncode == 1, both.stderr
    document = json.loads(both.stdout)
    first, second = document["results"]
    assert (first["accepted"], first["value"]) == (True, 250.5)
    assert (second["accepted"], second["value"]) == (False, 250.5)
    assert second["reason"] == "9000.0 mA/deg is above 500.0 mA/deg"
    assert document["parameters"]["controller.kp"] == 250.5
    assert document["parameters"]["controller.hp"] == 12
    # the same command's variants, in this process (cheaper than a process each)
    refused = hil_here(capsys, "tune", port, "safety.max_following_error_deg=30")
    assert refused.returncode == 1 and refused.stdout == ""
    assert refused.stderr.strip().splitlines() == [
        "safety.max_following_error_deg = 30 refused: safety.max_following_error_deg may "
        "only be lowered while it runs (20.0 deg now)"]


def test_hil_tune_refuses_bad_input_and_an_unreachable_or_parameterless_view_in_one_line(
        capsys: pytest.CaptureFixture[str]) -> None:
    closed = free_port()
    gone = hil_here(capsys, "tune", f"127.0.0.1:{closed}", "controller.kp=1")
    assert gone.returncode == 2 and gone.stdout == ""
    assert gone.stderr == f"hil: error: cannot connect to 127.0.0.1:{closed}: Connection " \
        "refused\n"
    for args, text in [(["1:2:3x", "--list"], "expected HOST:PORT"),
                       ([str(closed), "controller.kp"], "expected NAME=VALUE"),
                       ([str(closed)], "give NAME=VALUE to set, or --list")]:
        result = hil_here(capsys, "tune", *args)
        assert result.returncode == 2 and text in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    plain = LiveSink("127.0.0.1", 0)  # a live view without parameters: a replay's, say
    try:
        result = hil_here(capsys, "tune", f"127.0.0.1:{plain.port}", "--list")
    finally:
        plain.close()
    assert result.returncode == 2
    assert result.stderr.strip() == f"hil: error: 127.0.0.1:{plain.port} serves no parameters " \
        "(a live session of 'hil bench|servo run --live' does)"


def test_the_shipped_layouts_have_a_parameters_panel_beside_the_plots() -> None:
    for kind in ("bench", "servo"):
        layout = json.loads(Path(layout_path(kind)).read_text())
        assert "Parameters!hilparams" in layout["configById"]
        stack, leaves = [layout["layout"]], []
        while stack:
            node = stack.pop()
            if isinstance(node, str):
                leaves.append(node)
            else:
                stack += [node["first"], node["second"]]
        assert "Parameters!hilparams" in leaves


class FailingTuner(StandInTuner):
    def request(self, name: str, value: object, client: str, timeout_s: float = 5.0) -> Result:
        raise RuntimeError("the rebuild failed")


def test_the_reverse_channel_refuses_what_the_loop_cannot_answer() -> None:
    writer_end, loop_end = socket.socketpair()
    port = RemotePort(writer_end)
    server = PortServer(loop_end, FailingTuner())
    assert [s["name"] for s in port.specs()] == [
        "controller.kp", "controller.hp", "safety.max_following_error_deg"]
    failed = port.request("controller.kp", 3.0, "live client 1")
    assert (failed["accepted"], failed["reason"]) == (False, "RuntimeError: the rebuild failed")
    server.close()  # the run has ended
    ended = port.request("controller.kp", 3.0, "live client 1")
    assert (ended["accepted"], ended["reason"]) == (False, "the run has ended")
    assert port.specs() == []
