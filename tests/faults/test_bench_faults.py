"""Bench faults injected by the emulator, over the real wire, and the bridge's reactions.

Run level: ``hil bench run`` in lockstep against the in-process emulator over Modbus TCP on
127.0.0.1, its faults from the config's ``[faults]`` table. Link level: the driver against
the emulator over TCP and over RTU on a real pty pair.
"""

from __future__ import annotations

import json
import threading
import time

import pytest

from hil.bench.config import load_bench_config
from hil.cli.main import main
from hil.core.recording.reader import read_session
from hil.drivers.bench.modbus import LinkError, ModbusBenchDriver, ModbusLink, parse_bus_url
from hil.drivers.bench.safe_bench import SafeBench
from hil.emulators.bench.server import EmulatedBench
from hil.emulators.faults import parse_fault
from hil.emulators.null_modem import NullModem
from tests.pymodbus_bench import ANSWER_S

pytestmark = [pytest.mark.slow]

CONFIG = load_bench_config()


def bench_run(tmp_path, capsys, schedule, *flags):
    config = tmp_path / "faults.toml"
    config.write_text("[bus]\ngive_up_s = 5.0\n[faults]\nschedule = " + json.dumps(schedule)
                      + "\n")
    out = tmp_path / "run.mcap"
    status = main(["bench", "run", "--controller", "bc", "--cycles", "1", "--config",
                   str(config), "--out", str(out), "--json", *flags])
    captured = capsys.readouterr()
    kpis = json.loads(captured.out) if captured.out.strip().startswith("{") else {}
    events = [m["kind"] for _, m in read_session(out).topic("/events")]
    return status, kpis, events, captured.err


def test_link_lost_for_good_stops_the_run_with_faults(tmp_path, capsys):
    status, kpis, events, err = bench_run(tmp_path, capsys, ["drop@10"])
    # the bench never answers again: its relays cannot be confirmed safe after the run
    assert status == 4 and kpis["status"] == "unsafe"
    assert "bench.safe_state_unconfirmed" in events
    assert kpis["stop_reason"] == "link lost for 5 s"
    assert kpis["disturbed"] and kpis["faults"]["link_losses"] == 1
    assert kpis["faults"]["link_down_s"] == pytest.approx(5.0, abs=0.02)
    # the dead period is not counted as relays on: at most the 10 s before the loss
    assert kpis["overlap_s"] <= 10.0
    for kind in ("fault.injected", "link.lost", "link.gave_up", "session.stop"):
        assert kind in events
    lines = err.strip().splitlines()
    assert lines == [line for line in lines if line.startswith("hil: ")]
    assert any(line.startswith("hil: run disturbed (link lost for 5 s): link_losses 1")
               for line in lines)


def test_a_disturbed_run_detects_every_fault_and_completes(tmp_path, capsys):
    schedule = ["drop@3-3.2:every=2", "close@4-4.02", "freeze@6-8:device=meter",
                "weld@0:relay=P2", "exception@12-12.2:code=6", "load_step@20-21:va=100"]
    status, kpis, events, _err = bench_run(tmp_path, capsys, schedule)
    assert status == 3 and kpis["stop_reason"] == "completed"
    faults = kpis["faults"]
    assert events.count("fault.injected") == len(schedule)
    assert faults["retries"] > 0 and "link.retried" in events  # drop, close: retried
    assert "meter.stale" in events and faults["stale_readings"] >= 1        # freeze
    assert "relay.stuck" in events and faults["stuck_relays"] >= 1          # weld
    # close (every request for 0.02 s) and busy (0.2 s): lost, then restored after 0.5 s
    assert faults["link_losses"] == faults["reconnections"] == 2
    assert events.index("link.lost") < events.index("link.restored")


def test_a_load_step_over_a_signal_limit_stops_the_run(tmp_path, capsys):
    status, kpis, events, err = bench_run(tmp_path, capsys, ["load_step@2:va=900"],
                                          "--limit", "total_va<=1200")
    assert status == 1
    assert "limit violated" in err and "total_va" in err
    assert kpis["stop_reason"].startswith("limit")
    assert "fault.injected" in events


def test_a_request_error_ends_the_run_with_one_line(tmp_path, capsys):
    status, _kpis, _events, err = bench_run(tmp_path, capsys, ["exception@2:code=2,unit=2"])
    assert status == 2
    assert err.count("\n") == 1 and err.startswith("hil: error: ")
    assert "exception 0x02 (illegal data address)" in err


def driver_for(url, timeout_s=0.1, attempts=2):
    return ModbusBenchDriver(ModbusLink(parse_bus_url(url), timeout_s, attempts), CONFIG.map)


def emulator_with(*specs):
    return EmulatedBench(CONFIG.plant, CONFIG.server, [parse_fault(s) for s in specs])


def test_a_late_answer_is_a_timeout_and_a_prompt_one_is_not():
    # 0.5 s a request: 30 ms late is prompt and 1.5 s late is not, however loaded the machine
    with emulator_with("delay@0:ms=1500,unit=2", "delay@0:ms=30,unit=3") as emulator:
        driver = driver_for(emulator.serve_tcp(), timeout_s=0.5)
        t0 = time.monotonic()
        assert driver.read_levels()["q1"] == pytest.approx(55.0)
        assert time.monotonic() - t0 >= 0.03
        with pytest.raises(LinkError, match="after 2 attempt"):
            driver.read_power()
        assert driver.link.retries == 2
        # given up: the connection is closed, the next request goes on a new one
        assert driver.read_levels()["q1"] == pytest.approx(55.0)
        assert driver.link.connections == 2
        driver.close()


def test_a_late_answer_is_passed_over_by_its_transaction_id():
    """The first try's answer comes 0.6 s late, during the second try, on the same
    connection: passed over by its transaction id; the second try's answer is taken."""
    with emulator_with("delay@0-1:ms=600,unit=3") as emulator:
        driver = driver_for(emulator.serve_tcp(), timeout_s=0.5)
        # the fault's window ends (plant time 1 s) while the first try waits: the emulator
        # answers the second try at once, after the first one's late answer
        stepper = threading.Timer(0.1, emulator.step, args=(100,))
        stepper.start()
        assert driver.read_levels()["q1"] == pytest.approx(55.0)
        stepper.join()
        link = driver.link
        assert (link.retries, link.discarded, link.connections) == (1, 1, 1)
        driver.close()


def test_a_corrupt_crc_is_refused_and_retried_over_rtu():
    with NullModem() as modem, emulator_with("corrupt_crc@0-1") as emulator:
        emulator.serve_serial(modem.ports[1])
        driver = driver_for(f"modbus-rtu://{modem.ports[0]}?baud=115200", timeout_s=0.2)
        with pytest.raises(LinkError):
            driver.read_levels()
        assert driver.link.retries == 2
        emulator.step(100)  # plant time 1 s: the window is over
        with driver.link.patient(ANSWER_S):  # answered, however late a loaded machine is
            assert driver.read_levels()["q1"] == pytest.approx(55.0)
        driver.close()


def test_a_welded_relay_is_caught_by_the_read_back():
    with emulator_with("weld@0:relay=P1") as emulator:
        events = []
        bench = SafeBench(driver_for(emulator.serve_tcp(), timeout_s=ANSWER_S), _Clock(),
                          on_event=lambda kind, *a, **k: events.append(kind))
        bench.open()
        assert bench.set_relays({"P1": True}) == {"P1": "stuck"}
        assert bench.relays()["P1"] is False and events[-1] == "relay.stuck"
        assert bench.link_up  # a stuck relay is not a lost link
        assert bench.set_relays({"P2": True}) == {"P2": "switched"}
        bench.close()


class _Clock:
    def time_ns(self) -> int:
        return time.monotonic_ns()


def test_a_write_given_up_on_and_carried_out_late_is_no_foreign_master():
    """A Modbus server that serves a connection's requests in turn carries out a write after
    the master gave up on it: the relay is found where that write put it, after a later write
    of the run said otherwise. This run's own late write (``relay.late_write``), not another
    master: the run goes on. Another master's switch is still one (test_one_master.py)."""
    with emulator_with("delay@1-2:ms=1500,unit=1") as emulator:
        events = []
        bench = SafeBench(driver_for(emulator.serve_tcp(), timeout_s=0.1, attempts=1), _Clock(),
                          on_event=lambda kind, *a, **k: events.append(kind))
        bench.open()
        assert bench.set_relays({"M1": True}) == {"M1": "switched"}
        emulator.step(100)  # plant time 1 s: the relay module answers 1.5 s late
        with pytest.raises(LinkError):
            bench.safe_state()  # M1 off: given up on, carried out 1.5 s later
        emulator.step(100)  # the window is over
        with bench._driver.link.patient(ANSWER_S):
            assert bench.set_relays({"M1": True}) == {"M1": "unchanged"}  # as it knows it
            assert bench.readback()["M1"] is True
            deadline = time.monotonic() + ANSWER_S
            while emulator.plant.coils()[0] and time.monotonic() < deadline:
                time.sleep(0.01)
            assert bench.readback()["M1"] is False  # the late write
        assert (bench.stats.late_writes, bench.stats.foreign_changes) == (1, 0)
        assert "relay.late_write" in events and "relay.foreign_change" not in events
        bench.close()


def bench_with(emulator, events):
    """The safety layer over ``emulator``'s TCP server, each event kept as (kind, data); a lost
    link is retried 3 times, 50 ms apart."""
    return SafeBench(driver_for(emulator.serve_tcp(), timeout_s=ANSWER_S), _Clock(),
                     on_event=lambda kind, message, **data: events.append((kind, data)),
                     watchdog_polls=3, reconnect_interval_s=0.05)


def test_relays_confirmed_at_their_safe_level_after_a_run_ask_nothing_more():
    with emulator_with() as emulator:
        events = []
        bench = bench_with(emulator, events)
        bench.open()
        assert bench.set_relays({"P2": True}) == {"P2": "switched"}
        assert not bench.confirmed_safe  # written since
        bench.safe_state()
        asked = bench.stats.polls, bench._driver.link.connections
        assert bench.confirm_safe() is None
        assert (bench.stats.polls, bench._driver.link.connections) == asked
        bench.close()


def test_a_welded_relay_left_on_is_said_after_the_run():
    """P2 welded while on: the safe state cannot switch it off; after the run it is tried again
    as a lost link is, read back on: event bench.safe_state_unconfirmed and one line."""
    with emulator_with("weld@1:relay=P2") as emulator:
        events = []
        bench = bench_with(emulator, events)
        bench.open()
        assert bench.set_relays({"P2": True}) == {"P2": "switched"}
        emulator.step(100)  # plant time 1 s: welded on
        with pytest.raises(LinkError, match=r"relays \['P2'\] did not reach their safe level"):
            bench.safe_state()
        retries = bench.retries
        message = bench.confirm_safe()
        assert message == (f"relay P2 may still be on: read back from {emulator.url} after the "
                           "run, not at their safe level")
        assert events[-1] == ("bench.safe_state_unconfirmed", {
            "level": "error", "source": "bench", "url": emulator.url, "on": ["P2"], "off": [],
            "unknown": []})
        assert emulator.faults.hits["weld@1:relay=P2"] == 4 * 4  # 4 relays: the run, 3 tries
        assert bench.retries == retries  # the tries after the run are not the run's retries
        bench.close()


def test_after_a_lost_link_the_relays_are_driven_safe_again_once_the_bench_answers():
    """The link lost with P2 on (every answer dropped), then back: after the run the relays
    are driven to their safe levels and read back, nothing is said."""
    with emulator_with("drop@1-2") as emulator:
        events = []
        bench = SafeBench(driver_for(emulator.serve_tcp(), timeout_s=0.1, attempts=1),
                          _Clock(), on_event=lambda kind, message, **data: events.append(kind),
                          watchdog_polls=3, reconnect_interval_s=0.3)
        bench.open()
        assert bench.set_relays({"P2": True}) == {"P2": "switched"}
        emulator.step(100)  # every answer dropped
        emulator.plant.set_coils(3, [True])  # as if the loss's safe state never got through
        bench.lose_link("gone")
        assert not bench.confirmed_safe
        threading.Timer(0.2, emulator.step, args=(100,)).start()  # back during the first wait
        assert bench.confirm_safe() is None
        assert emulator.plant.coils()[:4] == [False] * 4
        assert events[-1] == "bench.safe" and "bench.safe_state_unconfirmed" not in events
        bench.close()
