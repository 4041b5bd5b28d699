"""Parameter subscriptions of a running session's live view, from outside: a user's script (a
process, from a folder of theirs) runs a servo session through ``hil.api.run_servo`` with
``--live``'s option and a tuner of its own, and independent Foxglove WebSocket clients
(tests/live/foxglove_client.py) subscribe to its parameters as Foxglove's Parameters panel
does. Every change is pushed to the subscribers, whoever made it: another client's set, or the
script's own tuner. The script's live view listens on 127.0.0.2, which is loopback too: its
clients may set parameters. The test stops the run with SIGINT once it has seen what it
needs; nothing depends on the machine's speed."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from typing import Any

import pytest

from hil.core.recording.live import LiveSink
from hil.core.recording.reader import read_session
from hil.core.tuning import PARAMS_SCHEMA, PARAMS_TOPIC
from tests.live.foxglove_client import FoxgloveClient
from tests.live.test_tune_run import ANSWER_S, CONNECT_S, free_port, user_env

pytestmark = [pytest.mark.slow]

#: the user's script: a long lockstep PID session; once the file GO exists, its own tuner
#: tightens the following-error limit (a change no live client asked for)
SCRIPT = """
import sys, threading, time
from pathlib import Path

from hil import api
from hil.core.recording.recording_options import RecordingOptions
from hil.errors import HilError

live, go = sys.argv[1], Path(sys.argv[2])


def tighten_on_go(tuner):
    def later():
        while not go.exists():
            time.sleep(0.01)
        print(tuner.request("safety.following_error_deg", 40.0, "my-script", timeout_s=60),
              flush=True)
    threading.Thread(target=later, daemon=True).start()


try:
    api.run_servo("pid", duration_s=600, out="run.mcap", quiet=True,
                  recording=RecordingOptions(live=live), tuner_started=tighten_on_go)
except HilError as exc:  # SIGINT: the session is finished with the KPIs so far
    print(exc, file=sys.stderr)
"""
WATCHED = ["controller.kp", "safety.following_error_deg"]


def updates_of(client: FoxgloveClient, name: str) -> list[Any]:
    return [p["value"] for p in client.updates if p["name"] == name]


@pytest.fixture(scope="module")
def watched_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """What a subscribed client saw while another client set the PID gain and the script's
    tuner tightened a limit; the run's stderr and session."""
    cwd = tmp_path_factory.mktemp("updates")
    (cwd / "tuned.py").write_text(SCRIPT)
    port = free_port()
    run = subprocess.Popen([sys.executable, "tuned.py", f"127.0.0.2:{port}", "go"], cwd=cwd,
                           env=user_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True)
    seen: dict[str, Any] = {}
    try:
        url = f"ws://127.0.0.2:{port}"
        watcher = FoxgloveClient(url, timeout_s=CONNECT_S, alive=run.poll)
        seen["listed"] = watcher.get_parameters([], "list", ANSWER_S)
        watcher.subscribe_parameter_updates(WATCHED)
        setter = FoxgloveClient(url, timeout_s=CONNECT_S, alive=run.poll)
        kp = seen["listed"]["controller.kp"]["value"] / 2
        seen["set"] = setter.set_parameters({"controller.kp": kp}, "kp", ANSWER_S)
        seen["kp_pushed"] = watcher.wait_for(
            lambda: kp in updates_of(watcher, "controller.kp"), ANSWER_S)
        setter.close()
        (cwd / "go").touch()
        seen["limit_pushed"] = watcher.wait_for(
            lambda: 40.0 in updates_of(watcher, "safety.following_error_deg"), ANSWER_S)
        seen["updates"] = list(watcher.updates)
        watcher.close()  # its subscriptions end with it
    except BaseException:
        run.kill()
        raise
    run.send_signal(signal.SIGINT)
    seen["stdout"], seen["stderr"] = run.communicate(timeout=120)
    seen["session"] = read_session(cwd / "run.mcap")
    return seen


def test_a_set_by_another_client_is_pushed_to_a_subscriber(watched_run: dict[str, Any]
                                                           ) -> None:
    kp = watched_run["listed"]["controller.kp"]["value"] / 2
    assert watched_run["set"] == {"controller.kp": pytest.approx(kp)}  # 127.0.0.2: loopback
    assert watched_run["kp_pushed"], watched_run["updates"]


def test_a_change_no_client_asked_for_is_pushed_to_a_subscriber(watched_run: dict[str, Any]
                                                                ) -> None:
    assert watched_run["limit_pushed"], watched_run["updates"]
    assert "accepted=True" in watched_run["stdout"]
    changes = [(m["parameter"], m["new"], m["client"])
               for _, m in watched_run["session"].topic("/params")]
    assert ("safety.following_error_deg", 40.0, "my-script") in changes
    # the subscriber was told the values in force, in the order they came into force
    for name in WATCHED:
        pushed = [p["value"] for p in watched_run["updates"] if p["name"] == name]
        recorded = [new for parameter, new, _ in changes if parameter == name]
        assert pushed and pushed[-1] == recorded[-1], (name, pushed, recorded)


def test_subscribing_and_leaving_cost_the_live_view_no_error(watched_run: dict[str, Any]
                                                             ) -> None:
    assert "Callback failed" not in watched_run["stderr"], watched_run["stderr"]
    live = watched_run["session"].metadata["live"]
    assert json.loads(live["client_errors"]) == {}
    assert json.loads(live["failed"]) == 0


class AcceptingPort:
    """A stand-in for the run's side of the parameters: two of them; a set is accepted and
    applied at tick 7."""

    def specs(self) -> list[dict[str, Any]]:
        return [{"name": "controller.kp", "value": 2.0}, {"name": "controller.kv", "value": 0.1}]

    def request(self, name: str, value: object, client: str) -> dict[str, Any]:
        return {"name": name, "accepted": True, "value": value, "reason": "", "tick": 7}


def test_a_subscriber_is_sent_each_newer_value_once() -> None:
    """The live view fed /params messages as a session's writer feeds them, and a client
    subscribed to one parameter: a live client's change comes once, as its set's answer (its
    record is not pushed too), a change from elsewhere as its record; an older value or another
    parameter not at all."""
    sink = LiveSink("127.0.0.1", 0, parameters=AcceptingPort())
    try:
        sink.add_topic(1, PARAMS_TOPIC, PARAMS_SCHEMA)
        client = FoxgloveClient(sink.url, timeout_s=CONNECT_S)
        client.subscribe_parameter_updates(["controller.kp"])
        client.get_parameters(["controller.kp"], "sync")  # the subscription is in place
        assert client.set_parameters({"controller.kp": 3.0}, "set") == {"controller.kp": 3.0}

        def record(name: str, new: float, tick: int, client: str = "my-script") -> None:
            sink.log(1, tick, {"parameter": name, "old": 0.0, "new": new, "unit": "",
                               "client": client, "tick": tick})

        record("controller.kp", 3.0, 7, "live client 1")  # the set's own record
        record("controller.kp", 3.5, 8, "live client 2")  # another set's, before its answer
        record("controller.kp", 2.5, 6)                     # older than the value sent
        record("controller.kv", 0.2, 8)                     # nobody subscribed to it
        record("controller.kp", 4.0, 9)                     # a script's change
        assert client.wait_for(lambda: 4.0 in [u["value"] for u in client.updates], 10)
        client.close()
    finally:
        sink.close()
    # one connection's control messages keep their order: anything pushed came before 4.0
    assert [(u["name"], u["value"]) for u in client.updates] == [
        ("controller.kp", 3.0), ("controller.kp", 4.0)]
    assert sink.stats().failed == 0
