"""Late answers over Modbus TCP, from outside: a real-time ``hil bench run --bench
modbus-tcp://...`` against ``hil emulate bench --tcp`` whose answers come 150 ms late for 3 s
(the ``delay`` fault; the run's requests wait 0.1 s). Each late answer comes on the connection
of its request, during the next try, and is passed over by its transaction id; the writes the
run gave up on and the bench carried out late are the run's own: no relay is taken for
switched by another master, the run goes on to its end (status 3: the bench misbehaved)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest

from hil.core.recording.reader import read_session
from tests.pymodbus_bench import short_cycle

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

ENV = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
#: a 2 s machining cycle, requests waiting 0.1 s, a lost link tried again every 0.5 s
CONFIG = "[bus]\ntimeout_s = 0.1\n" + short_cycle(2.0, dwell_s=0.5)


def test_late_answers_are_passed_over_and_no_relay_is_taken_for_another_masters(tmp_path):
    config = tmp_path / "late.toml"
    config.write_text(CONFIG)
    # the window in the emulator's time (seconds since it started): well after the run began
    # (its start-up takes a second or two on a loaded machine) and well before its 12 s end
    emulator = subprocess.Popen(
        [sys.executable, "-m", "hil", "emulate", "bench", "--tcp", "127.0.0.1:0", "--config",
         str(config), "--fault", "delay@5-8:ms=150"], cwd=tmp_path, env=ENV,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
    try:
        assert emulator.stdout is not None
        url = re.search(r"listening on (\S+)", emulator.stdout.readline()).group(1)
        run = subprocess.run(
            [sys.executable, "-m", "hil", "bench", "run", "--controller", "bc", "--cycles", "6",
             "--realtime", "--bench", url, "--config", str(config), "--json",
             "--out", "late.mcap"], cwd=tmp_path, env=ENV, capture_output=True, text=True,
            timeout=150)
    finally:
        emulator.terminate()
        _, emulator_err = emulator.communicate(timeout=10)
    assert "hil: fault: delay@5-8:ms=150.0,unit=0 injected" in emulator_err  # during the run
    assert run.returncode == 3, run.stderr
    kpis = json.loads(run.stdout)
    assert kpis["stop_reason"] == "completed" and kpis["faults"]["retries"] > 0
    events = [m for _, m in read_session(str(tmp_path / "late.mcap")).topic("/events")]
    kinds = {event["kind"] for event in events}
    assert not kinds & {"relay.foreign_change", "bench.foreign_master"}, kinds
    assert sum(e["data"]["passed_over"] for e in events if e["kind"] == "link.retried") > 0
    assert "hil: unsafe:" not in run.stderr
