"""Tuning running sessions from outside: ``hil servo run --live`` started as a user starts it
(a process, from a folder of theirs, the repository not on the path), driven by an independent
Foxglove WebSocket client (tests/live/foxglove_client.py, on the `websockets` package) and by
``hil tune``; what changed is read back from the session file. Each run is long enough to be
tuned and is stopped by the test with SIGINT once the client has seen what it needs (the
session is then finished with the KPIs so far): nothing depends on the machine's speed."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from hil.core.recording.reader import SessionData, read_session
from tests.drive_processes import patient_watchdogs
from tests.live.foxglove_client import FoxgloveClient

pytestmark = [pytest.mark.slow]

CONNECT_S = 60.0  # a process start on this shared 2-core machine can take 10 s and more
ANSWER_S = 60.0
WARNING = 1       # the Foxglove protocol's status level
INTERRUPTED = 130


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def user_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


def start_run(cwd: Path, port: int, *args: str) -> subprocess.Popen[str]:
    """A long servo run serving its parameters on ``port``; the test stops it."""
    return subprocess.Popen(
        [sys.executable, "-m", "hil", "servo", "run", "--duration", "600", "--quiet",
         "--live", str(port), "--out", str(cwd / "run.mcap"), *args],
        cwd=cwd, env=user_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def session_time_s(client: FoxgloveClient) -> float:
    """How far the run is: the log time of the last /drive/command the client received [s]."""
    messages = client.messages.get("/drive/command", [])
    return messages[-1][0] / 1e9 if messages else -1.0


def watch(port: int, run: subprocess.Popen[str]) -> FoxgloveClient:
    client = FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=CONNECT_S, alive=run.poll)
    assert client.wait_for(lambda: "/drive/command" in client.topics(), CONNECT_S)
    client.subscribe(["/drive/command"])
    return client


def run_until(client: FoxgloveClient, session_s: float) -> None:
    """Wait until the run's session time passed ``session_s``."""
    assert client.wait_for(lambda: session_time_s(client) > session_s, CONNECT_S), \
        (session_time_s(client), client.statuses)


def stop(run: subprocess.Popen[str], client: FoxgloveClient, cwd: Path) -> SessionData:
    """SIGINT to the run; the session it finished."""
    client.close()
    run.send_signal(signal.SIGINT)
    _, stderr = run.communicate(timeout=120)
    assert run.returncode == INTERRUPTED, stderr
    return read_session(cwd / "run.mcap")


def events(session: SessionData, kind: str) -> list[dict[str, Any]]:
    return [m["data"] for _, m in session.topic("/events") if m["kind"] == kind]


def status_of(client: FoxgloveClient, request_id: str, name: str) -> dict[str, Any]:
    assert client.wait_for(lambda: any(s.get("id", "").endswith(f":{request_id}:{name}")
                                       for s in client.statuses), ANSWER_S)
    return next(s for s in client.statuses if s.get("id", "").endswith(f":{request_id}:{name}"))


def rms_error(session: SessionData, start_ns: int, end_ns: int) -> float:
    errors = [m["error_deg"] for t, m in session.topic("/drive/command") if start_ns <= t < end_ns]
    assert len(errors) > 100
    return math.sqrt(sum(e * e for e in errors) / len(errors))


@pytest.fixture(scope="module")
def tuned_pid_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A lockstep PID run tuned from a WebSocket client and from ``hil tune``: what the
    client saw, and the session."""
    cwd = tmp_path_factory.mktemp("tuned")
    port = free_port()
    run = start_run(cwd, port, "--controller", "pid")
    seen: dict[str, Any] = {}
    try:
        client = watch(port, run)
        seen["listed"] = client.get_parameters([], "list")
        run_until(client, 1.0)  # a whole period of the 1 Hz sine before the change
        kp = seen["listed"]["controller.kp"]["value"]
        seen["kp"] = client.set_parameters({"controller.kp": kp / 10}, "kp", ANSWER_S)
        seen["too_high"] = client.set_parameters({"controller.kp": 1000.0}, "high", ANSWER_S)
        seen["too_high_status"] = status_of(client, "high", "controller.kp")
        seen["looser"] = client.set_parameters({"safety.following_error_deg": 90.0}, "loose",
                                               ANSWER_S)
        seen["looser_status"] = status_of(client, "loose", "safety.following_error_deg")
        seen["tune"] = subprocess.run(
            [sys.executable, "-m", "hil", "tune", f"127.0.0.1:{port}",
             "safety.following_error_deg=40", "--json"],
            cwd=cwd, env=user_env(), capture_output=True, text=True, timeout=120)
        seen["after"] = client.get_parameters(["controller.kp", "safety.following_error_deg"],
                                              "after")
        run_until(client, session_time_s(client) + 1.3)  # and one after it
    except BaseException:
        run.kill()
        raise
    seen["session"] = stop(run, client, cwd)
    return seen


def test_a_running_session_lists_its_parameters(tuned_pid_run: dict[str, Any]) -> None:
    listed = tuned_pid_run["listed"]
    assert {"controller.kp", "controller.kv", "controller.ti_us", "safety.following_error_deg",
            "safety.current_limit_mA"} <= set(listed)
    assert listed["controller.kp"]["type"] == "float64" and listed["controller.kp"]["value"] > 0


def test_a_gain_set_while_it_runs_takes_effect_at_its_tick_and_is_recorded(
        tuned_pid_run: dict[str, Any]) -> None:
    kp = tuned_pid_run["listed"]["controller.kp"]["value"]
    assert tuned_pid_run["kp"] == {"controller.kp": pytest.approx(kp / 10)}
    session = tuned_pid_run["session"]
    changed = [e for e in events(session, "param.changed") if e["parameter"] == "controller.kp"]
    assert len(changed) == 1
    change = changed[0]
    assert change["old"] == pytest.approx(kp) and change["new"] == pytest.approx(kp / 10)
    assert change["client"].startswith("live client ")
    # applied at a boundary after it was asked for; how many ticks later is the check's time
    # (the PID's stability) against a lockstep loop's pace: the machine's, not this test's
    assert change["tick"] >= change["asked_at_tick"] >= 0
    params = [m for _, m in session.topic("/params") if m["parameter"] == "controller.kp"]
    assert [p["tick"] for p in params] == [change["tick"]]
    # the tick's log time: /drive/command is logged every tick, in order
    commands = session.topic("/drive/command")
    at_ns = commands[change["tick"]][0]
    period = 1_000_000_000  # of the default 1 Hz sine: whole periods, whatever the phase
    before = rms_error(session, at_ns - period, at_ns)
    after = rms_error(session, at_ns + period // 5, at_ns + period // 5 + period)
    assert after > 2 * before, (before, after)


def test_hil_replay_serves_the_changes_as_they_were_recorded(
        tuned_pid_run: dict[str, Any]) -> None:
    """``hil replay`` serves ``/params`` (and the change's event) as the run recorded them."""
    session = tuned_pid_run["session"]
    recorded = session.topic("/params")
    assert recorded
    port = free_port()
    replay = subprocess.Popen(
        [sys.executable, "-m", "hil", "replay", session.path, "--live", str(port), "--speed",
         "0", "--wait", "20"], cwd=Path(session.path).parent, env=user_env(),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        client = FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=CONNECT_S,
                                alive=replay.poll)
        assert client.wait_for(lambda: {"/params", "/events"} <= set(client.topics()), 30)
        client.subscribe(["/params", "/events"])
        client.wait_for(lambda: client.closed, 60)
    finally:
        _, stderr = replay.communicate(timeout=60)
    assert replay.returncode == 0, stderr
    assert client.messages["/params"] == [(t, m) for t, m in recorded]
    served = [m["kind"] for _, m in client.messages["/events"]]
    assert served.count("param.changed") == len(events(session, "param.changed"))


def test_a_value_out_of_range_and_a_looser_safety_limit_are_refused_and_change_nothing(
        tuned_pid_run: dict[str, Any]) -> None:
    kp = tuned_pid_run["listed"]["controller.kp"]["value"]
    assert tuned_pid_run["too_high"] == {"controller.kp": pytest.approx(kp / 10)}
    status = tuned_pid_run["too_high_status"]
    assert status["level"] == WARNING and "rpm/deg" in status["message"]
    assert tuned_pid_run["looser"] == {"safety.following_error_deg": 45.0}
    status = tuned_pid_run["looser_status"]
    assert status["level"] == WARNING and "stricter" in status["message"]
    session = tuned_pid_run["session"]
    refused = {(e["parameter"], e["value"]) for e in events(session, "param.refused")}
    assert refused == {("controller.kp", 1000.0), ("safety.following_error_deg", 90.0)}
    changed = [e["parameter"] for e in events(session, "param.changed")]
    assert changed == ["controller.kp", "safety.following_error_deg"]  # kp/10, then hil tune


def test_hil_tune_tightens_a_safety_limit_of_a_running_session(
        tuned_pid_run: dict[str, Any]) -> None:
    tune = tuned_pid_run["tune"]
    assert tune.returncode == 0, tune.stderr
    (result,) = json.loads(tune.stdout)["results"]
    assert (result["accepted"], result["value"]) == (True, 40.0)
    assert tuned_pid_run["after"]["safety.following_error_deg"]["value"] == 40.0
    session = tuned_pid_run["session"]
    (change,) = [e for e in events(session, "param.changed")
                 if e["parameter"] == "safety.following_error_deg"]
    assert (change["old"], change["new"]) == (45.0, 40.0)
    assert change["client"].startswith("live client ")


def test_an_mpc_horizon_is_rebuilt_off_the_loop_and_swapped_at_a_tick(tmp_path: Path) -> None:
    port = free_port()
    run = start_run(tmp_path, port, "--controller", "mpc")
    try:
        client = watch(port, run)
        assert client.get_parameters(["controller.hp"], "hp0")["controller.hp"]["value"] == 50
        run_until(client, 0.1)
        assert client.set_parameters({"controller.hp": 30}, "hp", ANSWER_S) == {
            "controller.hp": 30}
        run_until(client, session_time_s(client) + 0.1)
    except BaseException:
        run.kill()
        raise
    session = stop(run, client, tmp_path)
    (change,) = events(session, "param.changed")
    assert (change["parameter"], change["old"], change["new"]) == ("controller.hp", 50, 30)
    assert change["tick"] > change["asked_at_tick"] >= 0
    # the prediction over H_p: 50 steps up to the swap's tick, 30 from it on
    commands = session.topic("/drive/command")
    at_ns = commands[change["tick"]][0]
    lengths = {(t >= at_ns, len(m["y_deg"])) for t, m in session.topic("/mpc/prediction")}
    assert lengths == {(False, 50), (True, 30)}
    assert json_loop(session)["missed"] == 0  # lockstep: the rebuild cost the loop no tick


def json_loop(session: SessionData) -> dict[str, Any]:
    return dict(json.loads(session.metadata["loop"]["servo"]))


@pytest.mark.realtime
def test_a_real_time_session_is_tuned_and_refuses_a_looser_limit(tmp_path: Path) -> None:
    # what is checked is the tuning, not this shared machine's timing: a drive process held up
    # must not end the run (a stall of 0.12 s tripped the safety net's stale share, and the
    # tuning was then refused as the run had ended)
    tolerant = tmp_path / "tolerant.toml"
    tolerant.write_text(patient_watchdogs())
    port = free_port()
    run = start_run(tmp_path, port, "--controller", "pid", "--realtime",
                    "--config", str(tolerant))
    try:
        client = watch(port, run)
        run_until(client, 0.1)
        assert client.set_parameters({"controller.kv": 0.3}, "kv", ANSWER_S) == {
            "controller.kv": 0.3}
        assert client.set_parameters({"safety.current_limit_mA": 2000.0}, "loose",
                                     ANSWER_S) == {"safety.current_limit_mA": 1000.0}
        assert status_of(client, "loose", "safety.current_limit_mA")["level"] == WARNING
        run_until(client, session_time_s(client) + 0.1)
    except BaseException:
        run.kill()
        raise
    session = stop(run, client, tmp_path)
    (change,) = events(session, "param.changed")
    assert (change["parameter"], change["new"]) == ("controller.kv", 0.3)
    assert change["tick"] >= change["asked_at_tick"] >= 0
    (refusal,) = events(session, "param.refused")
    assert (refusal["parameter"], refusal["value"]) == ("safety.current_limit_mA", 2000.0)
