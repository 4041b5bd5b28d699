"""``hil servo run`` against a drive emulator process that faults on purpose: the run ends
with one error line (no traceback text, no python-can log lines on stderr), the session
records the EMCY, and the emulator reports what it injected."""

from __future__ import annotations

import pytest

from hil import api
from hil.cli.main import main
from hil.core.recording.reader import read_session
from tests.drive_processes import patient_watchdogs

pytestmark = [pytest.mark.timeout(90), pytest.mark.slow]


@pytest.mark.realtime
def test_an_emcy_during_a_run_over_socketcand_ends_it_with_one_line(tmp_path, capsys):
    config = tmp_path / "drive.toml"
    # generous watchdogs: on a loaded machine only the injected fault may end the run
    config.write_text(patient_watchdogs("rx_timeout_us = 5000\n"))
    out = tmp_path / "servo.mcap"
    # 0.5 s of the run's SYNCs (clock="sync": the emulator's time passes only with SYNCs,
    # which start with the run's loop, after it enabled the drive): 1000 ticks into the run,
    # however long the start took on a loaded machine
    with api.start_drive_emulator(config, faults=["emcy@0.5:code=0x4310"], clock="sync",
                                  harden=True) as emulator:
        status = main(["servo", "run", "--controller", "pid", "--drive", emulator.url,
                       "--config", str(config), "--duration", "60", "--realtime",
                       "--reference", "hold:position=0", "--out", str(out)])
        injected = emulator.fault_events()
    err = capsys.readouterr().err
    assert status == 2
    assert err.count("\n") == 1 and err.startswith("hil: error: drive node 1 reports FAULT")
    assert "0x4310" in err and "Traceback" not in err
    assert injected and injected[0].startswith("emcy@0.5:code=0x4310 injected at t=")
    events = read_session(out).topic("/events")
    emcy = [m for _, m in events if m["kind"] == "drive.emcy"]
    assert emcy and emcy[0]["data"]["code"] == 0x4310 and emcy[0]["data"]["while_driving"]
