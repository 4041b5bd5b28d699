"""Live view: a real WebSocket client against real sessions, replays and a stalled client."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.cli.main import main
from hil.core.clock import RealtimeClock
from hil.core.loop import FunctionTask
from hil.core.recording.live import flatten
from hil.core.recording.reader import read_session
from hil.core.recording.recorder import RecordingOptions
from hil.core.session import Session
from tests.drive_processes import patient_watchdogs
from tests.live.foxglove_client import FoxgloveClient, stalled_client
from tests.pymodbus_bench import short_config

pytestmark = [pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
CONNECT_S = 60.0  # a process start on this shared 2-core machine can take 10 s and more
SERVO_TOPICS = ["/drive/command", "/drive/feedback", "/mpc/prediction", "/events",
                "/loop/servo/timing"]


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def start_hil(*args: str) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", "hil", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def assert_json_schemas(client: FoxgloveClient, topics: list[str]) -> None:
    advertised = client.topics()
    for topic in topics:
        channel = advertised[topic]
        assert channel["encoding"] == "json", topic
        assert channel["schemaEncoding"] == "jsonschema", topic
        schema = json.loads(channel["schema"])
        assert schema["type"] == "object" and schema["properties"], topic


@pytest.fixture(scope="module")
def servo_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 1 s lockstep servo session split every 0.25 s (CDR drive topics, JSON events and
    timing): servo_000.mcap ... servo_003.mcap."""
    path = tmp_path_factory.mktemp("live") / "servo.mcap"
    assert main(["servo", "run", "--controller", "mpc", "--duration", "1", "--split-duration",
                 "0.25", "--out", str(path), "--json"]) == 0
    return path


@pytest.mark.realtime
def test_realtime_servo_run_serves_its_topics_with_json_schemas_decimated(
        tmp_path: Path) -> None:
    # what is checked is the live view, not this shared machine's timing: a drive process held
    # up must not end the run
    tolerant = tmp_path / "tolerant.toml"
    tolerant.write_text(patient_watchdogs())
    port = free_port()
    out = tmp_path / "servo.mcap"
    run = start_hil("servo", "run", "--controller", "pid", "--realtime", "--duration", "2",
                    "--config", str(tolerant), "--live", str(port), "--out", str(out), "--json")
    try:
        client = FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=CONNECT_S, alive=run.poll)
        assert client.ws.subprotocol == "foxglove.sdk.v1"
        assert client.wait_for(lambda: set(SERVO_TOPICS) - {"/mpc/prediction"}
                               <= set(client.topics()), 10)
        topics = [t for t in SERVO_TOPICS if t in client.topics()]
        assert_json_schemas(client, topics)
        timing_schema = json.loads(client.topics()["/loop/servo/timing"]["schema"])
        assert {"lateness_us_max", "compute_us_mean"} <= set(timing_schema["properties"])
        client.subscribe(topics)
        assert client.wait_for(lambda: len(client.messages.get("/loop/servo/timing", [])) >= 1
                               and len(client.messages.get("/drive/feedback", [])) >= 20, 10)
        client.close()
    finally:
        _, stderr = run.communicate(timeout=60)
    assert f"ws://127.0.0.1:{port}" in stderr
    feedback = client.messages["/drive/feedback"]
    assert {"position_deg", "current_mA", "cycle"} <= set(feedback[0][1])
    span_s = (feedback[-1][0] - feedback[0][0]) / 1e9
    assert (len(feedback) - 1) / span_s <= 105  # 2 kHz on the drive, 100 Hz live by default
    timing = client.messages["/loop/servo/timing"][0][1]
    assert timing["lateness_us_max"] == max(timing["lateness_us"])


def test_replay_of_a_truncated_session_serves_the_recorded_messages(
        servo_session: Path, tmp_path: Path) -> None:
    files = sorted(servo_session.parent.glob("servo_*.mcap"))
    assert len(files) >= 3
    for file in files:
        shutil.copy(file, tmp_path)
    last = tmp_path / files[-1].name
    last.write_bytes(last.read_bytes()[:last.stat().st_size // 2])  # the writer was killed
    truncated = tmp_path / "servo.mcap"  # the series by its unsplit name
    recorded = read_session(truncated)
    assert recorded.recovered and len(recorded.files) == len(files)
    expected = dict(recorded.topic("/drive/feedback"))
    port = free_port()
    replay = start_hil("replay", str(truncated), "--live", str(port), "--speed", "0",
                       "--wait", "20", "--live-rate", "/drive/feedback=200")
    try:
        client = FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=CONNECT_S,
                                alive=replay.poll)
        assert client.wait_for(lambda: set(SERVO_TOPICS) <= set(client.topics()), 10)
        assert_json_schemas(client, SERVO_TOPICS)
        client.subscribe(SERVO_TOPICS)
        client.wait_for(lambda: client.closed, 20)
    finally:
        _, stderr = replay.communicate(timeout=30)
    assert replay.returncode == 0, stderr
    assert "damaged or unfinished" in stderr
    served = client.messages["/drive/feedback"]
    # 200 Hz of the 2 kHz feedback over what survived the cut, each the recorded message
    assert abs(len(served) - len(expected) / 10) <= 2
    for t_ns, message in served:
        assert message == pytest.approx(expected[t_ns])
    prediction = client.messages["/mpc/prediction"][0][1]
    assert prediction["y_deg_max"] == pytest.approx(max(prediction["y_deg"]))


def _run_ticks(path: Path, port: int, with_stalled_client: bool) -> tuple[int, dict]:
    """1.5 s at 1 kHz, each tick a 7.2 kB message served live (10.8 MB in all: more than the
    kernel's buffers and the SDK's queue for a stalled client hold).

    Returns the ticks (run or skipped) and the file's ``live`` metadata."""
    session = Session(str(path), RealtimeClock(), 1e-3, kind="live-test", handle_signals=False,
                      recording=RecordingOptions(live=f"127.0.0.1:{port}",
                                                 live_rates={"/tick": 0}))
    topic = session.topic("/tick", {"type": "object", "title": "Tick", "properties": {
        "v": {"type": "array", "items": {"type": "number"}}}})
    payload = {"v": [0.123456789] * 600}
    session.add_task(FunctionTask("tick", 1, write=lambda t: topic.log(t, payload)))
    sock = None
    if with_stalled_client:
        session.recorder.flush()  # hand the topics to the writer, which advertises them
        sock = stalled_client("127.0.0.1", port, ["/tick", "/loop/tick/timing"], CONNECT_S)
    try:
        session.run(duration_s=1.5)
    finally:
        session.close()
        if sock is not None:
            sock.close()
    stats = session.loop.stats["tick"]
    data = read_session(path)
    assert len(data.topic("/tick")) == stats.runs  # the file lost nothing
    return stats.runs + stats.missed, data.metadata.get("live", {})


@pytest.mark.realtime
def test_a_stalled_client_overflows_its_own_queue_and_the_file_loses_nothing(
        tmp_path: Path) -> None:
    """What a stalled client costs the loop in skipped ticks is a wall-clock figure:
    ``benchmarks/live.py --stalled`` measures it beside a run without the live view."""
    alone_ticks, alone_live = _run_ticks(tmp_path / "a.mcap", free_port(), False)
    stalled_ticks, stalled_live = _run_ticks(tmp_path / "b.mcap", free_port(), True)
    assert alone_ticks > 0 and json.loads(alone_live["sent"]) == {}  # nobody subscribed
    sent = json.loads(stalled_live["sent"])["/tick"]
    assert sent >= 0.9 * stalled_ticks  # served every tick to the client that never read
    # the SDK's queue for the client overflowed and dropped, and said so
    assert int(stalled_live["client_queue_full"]) >= 1


def test_live_flag_errors_are_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["servo", "run", "--controller", "pid", "--live", "70000"])
    assert exc.value.code == 2
    assert "--live" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["servo", "run", "--controller", "pid", "--live-rate", "/drive/feedback=fast"])
    assert "--live-rate" in capsys.readouterr().err
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["servo", "run", "--controller", "pid", "--duration", "0.01",
                     "--live", str(port)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("hil: error: --live: cannot serve on 127.0.0.1:") and len(err) == 1
    assert main(["replay", "missing.mcap"]) == 2
    assert "--live" in capsys.readouterr().err


def test_layouts_are_shipped_and_name_topics_and_fields_of_real_sessions(
        servo_session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["layout", "bench"]) == 0
    bench_path = capsys.readouterr().out.strip()
    assert Path(bench_path).is_file() and Path(bench_path).parent.name == "layouts"
    out = tmp_path / "servo.json"
    assert main(["layout", "servo", "--out", str(out)]) == 0
    servo = json.loads(out.read_text())
    data = read_session(servo_session)
    assert len(data.files) > 1
    fields = {topic: set(msgs[0][1]) for topic, msgs in data.messages.items()}
    for name in ("/drive/command", "/drive/feedback", "/mpc/prediction", "/loop/servo/timing"):
        fields[name] = set(flatten(data.topic(name)[0][1]))
    paths = [p["value"] for cfg in servo["configById"].values() for p in cfg.get("paths", [])]
    assert len(paths) >= 8
    for path in paths:
        topic, _, field = path.partition(".")
        assert field.split(".")[0] in fields[topic], path
    for layout in (servo, json.loads(Path(bench_path).read_text())):
        panels = set(layout["configById"])
        leaves: list[str] = []
        stack = [layout["layout"]]
        while stack:
            node = stack.pop()
            if isinstance(node, str):
                leaves.append(node)
            else:
                stack += [node["first"], node["second"]]
        assert sorted(leaves) == sorted(panels)


@pytest.mark.parametrize(("device", "where", "topic", "field"), [
    ("drive", "--socketcand", "/emulator/drive", "position_deg"),
    ("bench", "--tcp", "/bench/power", "total_va"),
])
def test_emulators_serve_their_state_live(device: str, where: str, topic: str,
                                          field: str) -> None:
    port = free_port()
    emulator = start_hil("emulate", device, where, "127.0.0.1:0", "--live", str(port))
    try:
        client = FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=CONNECT_S,
                                alive=emulator.poll)
        assert client.wait_for(lambda: {topic, "/events"} <= set(client.topics()), 10)
        assert_json_schemas(client, [topic, "/events"])
        client.subscribe([topic])
        assert client.wait_for(lambda: len(client.messages.get(topic, [])) >= 3, 10)
        client.close()
    finally:
        emulator.terminate()
        _, stderr = emulator.communicate(timeout=30)
    assert f"ws://127.0.0.1:{port}" in stderr
    assert isinstance(client.messages[topic][-1][1][field], float)


@contextlib.contextmanager
def taken_beside_a_free_port() -> Iterator[int]:
    """A listening port P + 1 held for the block, P free, both below 32768; P + 1."""
    for port in range(20_001, 32_767, 2):
        with socket.socket() as taken:
            try:
                taken.bind(("127.0.0.1", port + 1))
                with socket.socket() as probe:
                    probe.bind(("127.0.0.1", port))
            except OSError:
                continue
            taken.listen()
            yield port + 1
            return
    raise AssertionError("no free pair of ports below 32768")


def test_demo_live_takes_two_ports_and_says_which_is_taken(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # the EEC (and later the servo) sessions on PORT, the BC session beside it on PORT + 1:
    # PORT + 1 taken here, PORT free and below the kernel's ephemeral ports (32768 and up),
    # which the other tests' servers and clients take: none of them can take it meanwhile
    with taken_beside_a_free_port() as busy:
        assert main(["demo", "--out", str(tmp_path), "--live", str(busy - 1)]) == 2
    assert f"cannot serve on 127.0.0.1:{busy}" in capsys.readouterr().err
    assert not list(tmp_path.glob("*.mcap"))


def _reset_after_subscribing(url: str) -> None:
    """A client that connects, subscribes to everything, then drops the TCP connection with
    a reset (as a browser tab killed mid-stream does)."""
    client = FoxgloveClient(url, CONNECT_S)
    client.subscribe(list(client.topics()))
    sock = client.ws.socket
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()


def test_clients_that_come_and_go_cost_one_stderr_line_per_reason(tmp_path: Path) -> None:
    port = free_port()
    out = tmp_path / "churn.mcap"
    config = short_config(tmp_path)  # a 4 s machining cycle
    run = start_hil("bench", "run", "--controller", "bc", "--realtime", "--cycles", "2",
                    "--config", str(config), "--live", str(port), "--out", str(out))
    try:
        for _ in range(30):
            _reset_after_subscribing(f"ws://127.0.0.1:{port}")
        _, stderr = run.communicate(timeout=60)
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == 0, stderr
    lines = [line for line in stderr.splitlines() if line.startswith("hil: live view: ")
             and "live view on" not in line]
    live = read_session(str(out)).metadata.get("live", {})
    errors = json.loads(live.get("client_errors", "{}"))
    # one line per reason, whatever reasons the load brings (3 or 4 seen): repeats are counted
    assert len(lines) == len(errors) < sum(errors.values()), stderr
