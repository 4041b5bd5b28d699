"""A SIGKILLed recording leaves a truncated file; every complete chunk must be recovered."""

import os
import signal
import time

import pytest
from mcap.reader import make_reader

from hil.core.reader import read_session

RATE_HZ = 2000

CHILD = """
import time
from hil.core.recorder import Recorder
rec = Recorder({path!r})
topic = rec.topic("/seq", {{"type": "object", "title": "Seq"}})
t0 = time.monotonic()
k = 0
while True:
    target = t0 + k / {rate}
    while time.monotonic() < target:
        time.sleep(0.0002)
    topic.log(int(target * 1e9), {{"k": k, "pad": "x" * 40}})
    if k % 100 == 0:
        print(k, flush=True)
    k += 1
"""


def test_sigkill_loses_at_most_about_one_second(tmp_path, run_python):
    path = tmp_path / "crash.mcap"
    child = run_python(CHILD.format(path=str(path), rate=RATE_HZ))
    try:
        last_reported = -1
        t_start = time.monotonic()
        while time.monotonic() - t_start < 3.5:
            line = child.stdout.readline()
            if not line:
                pytest.fail(f"child died early: {child.stderr.read()}")
            last_reported = int(line)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=10)
    assert last_reported > RATE_HZ * 2  # it really recorded for a while

    with open(path, "rb") as f, pytest.raises(Exception):  # noqa: B017 - the stock reader fails
        list(make_reader(f).iter_messages())

    data = read_session(path)
    assert data.recovered
    ks = [m["k"] for _, m in data.topic("/seq")]
    assert ks == list(range(len(ks)))  # a gap-free prefix of what was logged
    lost_messages = last_reported - len(ks)
    # flush every 1 s; allow 0.75 s more for a loaded 2-core machine
    assert lost_messages <= 1.75 * RATE_HZ, f"lost {lost_messages} messages"
    assert_lost_bytes_mark_the_readable_prefix(path, data, tmp_path)


def assert_lost_bytes_mark_the_readable_prefix(path, data, tmp_path):
    """Cut at ``size - lost_bytes`` the file reads the same with nothing lost; one byte
    shorter, the last record read is incomplete and is lost."""
    blob = path.read_bytes()
    readable = len(blob) - data.lost_bytes
    assert 0 < readable <= len(blob)
    prefix = tmp_path / "prefix.mcap"
    prefix.write_bytes(blob[:readable])
    again = read_session(prefix)
    assert again.lost_bytes == 0 and again.messages == data.messages
    shorter = tmp_path / "shorter.mcap"
    shorter.write_bytes(blob[:readable - 1])
    cut = read_session(shorter)
    assert cut.lost_bytes > 0
    assert sum(map(len, cut.messages.values())) <= sum(map(len, data.messages.values()))


def test_report_summarises_the_truncated_file(tmp_path, run_python, capsys):
    path = tmp_path / "crash.mcap"
    child = run_python(CHILD.format(path=str(path), rate=RATE_HZ))
    try:
        for _ in range(30):  # about 1.5 s of recording
            assert child.stdout.readline()
        time.sleep(0.3)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=10)
    from hil.cli.main import main

    assert main(["report", str(path), "--json"]) == 0
    import json

    summary = json.loads(capsys.readouterr().out)
    assert summary["recovered"] is True
    assert summary["topics"]["/seq"] >= RATE_HZ // 2
    assert summary["duration_s"] > 0
    assert set(summary) >= {"topics", "duration_s", "recovered", "loop", "kpis"}
