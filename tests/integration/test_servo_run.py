"""``hil servo run``: controllers closing the loop through the CiA 402 drive link.

Lockstep runs go through the emulated drive on a python-can virtual bus (real frames, real SDO
set-up, the emulator's plant); one run goes over socketcand to a separate emulator process
(``hil emulate drive``) on 127.0.0.1. No wall-clock timing is asserted: the real-time run
checks the split read/write path, not its lateness (``benchmarks/servo.py`` measures that).
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from hil.cli.main import main
from hil.controllers.servo.references import parse_scenario
from hil.controllers.servo.sim import simulate
from hil.core.recording.reader import read_session
from hil.drivers.canopen import DriveFaultError
from hil.servo.config import drive_for
from hil.servo.run import ServoRunOptions, make_controller, run_servo
from tests.drive_processes import start_drive_emulator, stop_drive_emulator

REPO = Path(__file__).resolve().parents[2]
INCREMENT_DEG = 360.0 / 2**20  # the emulated encoder's resolution
DESIGN_KEYS = {"controller", "max_error_deg", "max_error_pct", "rms_error_deg",
               "cumulative_error_deg", "step_us", "deadline_misses", "ticks", "mcap"}
pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]


def run(tmp_path: Path, name: str, on_started=None, **settings) -> tuple[dict, object]:
    result = run_servo(ServoRunOptions(out=str(tmp_path / f"{name}.mcap"), **settings),
                       on_started=on_started)
    return result.kpis, read_session(result.session_path)


@pytest.mark.parametrize("controller", ["mpc", "pid"])
def test_integral_action_removes_a_constant_disturbance_torque(tmp_path, controller):
    # 300 mA of load torque from t = 0.1 s, through the emulator's plant (drive.toml)
    disturbance = {"emulator": {"disturbance": {"constant_mA": 300.0, "start_s": 0.1}}}
    kpis, data = run(tmp_path, controller, controller=controller, reference="hold:position=0",
                     duration_s=1.0, drive_overrides=disturbance)
    command, feedback = data.arrays("/drive/command"), data.arrays("/drive/feedback")
    t, error = command["t_s"], np.abs(command["error_deg"])
    assert kpis["ticks"] == 2000 and kpis["stale_feedback"] == 0
    assert error[t < 0.1].max() == 0.0
    assert error.max() > 20 * INCREMENT_DEG  # the torque did push the axis away...
    assert error[t >= 0.8].max() <= INCREMENT_DEG + 1e-9  # ...and no offset is left
    # the controller ends up supplying the torque: -300 mA commanded, and applied by the drive
    assert command["command_mA"][-1] == pytest.approx(-300.0, abs=2.0)
    assert feedback["current_mA"][-1] == pytest.approx(-300.0, abs=1.0)


def decode_wire(observer) -> tuple[np.ndarray, np.ndarray]:
    """Target torque of every RPDO1 (0x201) and torque actual of every TPDO2 (0x281) seen on
    the bus [mA: 1 unit = 1 per mille of the 1000 mA rated current]."""
    targets, actuals = [], []
    while (msg := observer.recv(0)) is not None:
        if msg.arbitration_id == 0x201:
            targets.append(struct.unpack_from("<Hh", msg.data)[1])
        elif msg.arbitration_id == 0x281:
            actuals.append(struct.unpack_from("<ih", msg.data)[1])
    return np.asarray(targets, float), np.asarray(actuals, float)


class Alternating:
    """Asks for +-5000 mA, a sign every 10 ms: far beyond any limit, on purpose."""

    def __init__(self, reference, params):
        pass

    def step(self, position_deg, t_s):
        return 5000.0 if int(t_s / 0.01) % 2 == 0 else -5000.0


@pytest.mark.parametrize("driver_limit", [1000.0, 600.0])
def test_the_current_limit_is_never_exceeded_on_the_wire(tmp_path, driver_limit):
    """A controller that asks for 5 A: the driver's clamp keeps the wire within the limit,
    and the drive's max torque 0x6072 holds it for the run (its own value back after)."""
    observers, max_torque = [], []

    def attach(master):
        observers.append(master.emulator.attach_bus())
        max_torque.append(master.emulator.node._values[(0x6072, 0)])

    overrides = {"master": {"current_limit_mA": driver_limit}}
    kpis, data = run(tmp_path, "limit", on_started=attach, controller=Alternating,
                     reference="sine:amplitude=2,frequency=10", duration_s=0.5,
                     drive_overrides=overrides)
    [observer] = observers
    try:
        targets, actuals = decode_wire(observer)
    finally:
        observer.shutdown()
    assert targets.size >= 1000 and actuals.size >= 1000
    assert np.abs(targets).max() == driver_limit  # reached: the limit was tested...
    assert np.abs(actuals).max() <= driver_limit  # ...and never exceeded, sent or applied
    assert max_torque == [driver_limit]  # the drive's own max torque (per mille) in the run
    assert np.abs(data.arrays("/drive/feedback")["command_mA"]).max() <= driver_limit
    assert np.abs(data.arrays("/drive/command")["command_mA"]).max() == 5000.0
    assert kpis["clamped_commands"] == 1000 and kpis["current_limit_mA"] == driver_limit


@pytest.mark.parametrize(("controller", "reference", "umax", "tolerance_deg"), [
    ("mpc", "sine:amplitude=2,frequency=10", 12000.0, 2 * INCREMENT_DEG),
    ("pid", "disturbance:torque=1200,start=0.1,end=0.35", 1000.0, 0.1),
])
def test_the_loop_through_can_reproduces_the_offline_simulation(tmp_path, controller,
                                                                 reference, umax, tolerance_deg):
    """Same model, same controller: through CAN the trajectory matches servo_sim.simulate up to
    the wire's quantisation (1 mA, one encoder increment). A delay of one tick more would be
    off by ~0.08 deg on the sine, a disturbance of the wrong sign by ~47 deg in Fig. 16."""
    config = ServoRunOptions(controller=controller, reference=reference, umax=umax,
                            duration_s=1.0, out=str(tmp_path / "can.mcap"),
                            drive_overrides=drive_for(umax),  # 12 A: the motor's rated
                            allow_higher_current=umax > 1000.0)
    run_servo(config)
    position = read_session(config.out).arrays("/drive/feedback")["position_deg"]
    scenario = parse_scenario(reference)
    offline = simulate(make_controller(config, scenario), scenario.reference, 1.0,
                       current_limit_ma=umax, disturbance=scenario.disturbance)
    assert position.size == offline.position.size == 2000
    assert np.abs(position - offline.position).max() <= tolerance_deg
    if scenario.disturbance is not None:
        assert position.max() > 15.0  # pushed the positive way by the +1200 mA pulse, and back
        assert abs(position[-1]) < 0.5


def test_cli_json_keys_mcap_topics_and_report(tmp_path, capsys):
    out = tmp_path / "cli.mcap"
    twelve_amps = tmp_path / "drive.toml"  # the paper's motor: rated 12 A, its drive allows it
    twelve_amps.write_text("[master]\ncurrent_limit_mA = 12000\n"
                           "[emulator]\nmax_torque_permille = 12000\n")
    code = main(["servo", "run", "--controller", "mpc", "--ht", "4", "--hu", "4", "--duration",
                 "0.2", "--reference", "sine:amplitude=2,frequency=10", "--config",
                 str(twelve_amps), "--out", str(out), "--json"])
    assert code == 0
    kpis = json.loads(capsys.readouterr().out)
    assert set(kpis) >= DESIGN_KEYS
    assert set(kpis["step_us"]) == {"median", "p99", "max"}
    assert kpis["controller"] == "mpc" and kpis["ticks"] == 400 and kpis["mcap"] == str(out)
    assert kpis["deadline_misses"] == 0  # lockstep
    assert 0 < kpis["max_error_deg"] < 2.0
    assert kpis["max_error_pct"] == pytest.approx(100 * kpis["max_error_deg"] / 2.0)
    assert kpis["cumulative_error_deg"] >= kpis["max_error_deg"] >= kpis["rms_error_deg"] > 0
    assert 0 < kpis["step_us"]["median"] <= kpis["step_us"]["p99"] <= kpis["step_us"]["max"]

    data = read_session(out)
    counts = data.topic_counts
    for topic in ("/drive/command", "/drive/feedback", "/mpc/prediction"):
        assert counts[topic] == 400, topic
    assert counts["/events"] >= 3 and counts["/loop/servo/timing"] >= 1
    prediction = data.topic("/mpc/prediction")[10][1]
    assert len(prediction["u_mA"]) == 4 and len(prediction["y_deg"]) == 50
    assert data.metadata["session"]["kind"] == "servo"
    assert json.loads(data.metadata["kpis"]["json"])["ticks"] == 400
    assert "drive.toml" in data.attachments
    kinds = {m["kind"] for _, m in data.topic("/events")}
    assert {"drive.enabled", "drive.safe_stop", "session.stop"} <= kinds

    png = tmp_path / "cli.png"
    assert main(["report", str(out), "--out", str(png), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["kind"] == "servo" and report["kpis"]["ticks"] == 400
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_disturbance_scenario_and_explicit_mpc(tmp_path, capsys):
    """Fig. 16 with the explicit MPC (H_t = H_u = 3, as on the paper's drive): the 1200 mA pulse
    beats the 1000 mA limit, pushes the axis away, and the controller brings it back."""
    out = tmp_path / "fig16.mcap"
    assert main(["servo", "run", "--controller", "empc", "--ht", "3", "--hu", "3",
                 "--reference", "disturbance:torque=1200,start=0.1,end=0.35",
                 "--duration", "1.2", "--out", str(out), "--json"]) == 0
    kpis = json.loads(capsys.readouterr().out)
    assert kpis["max_error_deg"] > 10.0 and kpis["max_error_pct"] is None
    assert kpis["peak_current_mA"] == pytest.approx(1000.0)
    assert kpis["empc_fallbacks"] >= 0 and kpis["solver_paths"]["explicit"] > 0
    data = read_session(out)
    command = data.arrays("/drive/command")
    assert abs(command["error_deg"][-1]) < 0.01  # settled back at the set-point
    pushes = [m["data"]["torque_mA"] for _, m in data.topic("/events")
              if m["kind"] == "servo.disturbance"]
    assert pushes == [1200, 0]
    assert command["disturbance_mA"].max() == 1200


def test_a_drive_fault_stops_the_run_and_the_session_keeps_it(tmp_path):
    """The emulated drive trips at 500 mA; the MPC asks for more at once: the master raises,
    the loop stops, and the finished session file holds the fault and the KPIs so far."""
    out = tmp_path / "fault.mcap"
    config = ServoRunOptions(controller="mpc", umax=1000.0, duration_s=1.0, out=str(out),
                            drive_overrides={"emulator": {"overcurrent_trip_mA": 500}})
    with pytest.raises(DriveFaultError, match=r"EMCY 0x2310.*session recorded to .*fault.mcap"):
        run_servo(config)
    data = read_session(out)
    assert not data.recovered  # finished properly, summary and index written
    kinds = [m["kind"] for _, m in data.topic("/events")]
    assert "drive.emcy" in kinds and "drive.fault" in kinds
    kpis = json.loads(data.metadata["kpis"]["json"])
    assert kpis["ticks"] < 2000 and "over-current" in kpis["error"]


@pytest.mark.parametrize(("argv", "message"), [
    (["--reference", "sine:amplitude=2,freq=3"], "bad parameter 'freq=3'"),
    (["--reference", "square:period=1"], "unknown kind 'square'"),
    (["--ht", "1"], "H_t >= 2"),
    (["--ht", "60"], "must not exceed H_p"),
    (["--settle", "3", "--duration", "1"], "--settle"),
    (["--drive", "nonsense"], "expected emulated, ethercat://IFACE[?slave=N], socketcand://HOST:PORT"),
])
def test_bad_values_give_one_clear_line(tmp_path, capsys, argv, message):
    out = tmp_path / "bad.mcap"
    assert main(["servo", "run", "--controller", "mpc", "--out", str(out), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hil: error: ") and "\n" not in err and message in err
    assert not out.exists()


@pytest.mark.realtime
def test_realtime_run_uses_the_split_read_write_path_and_an_emulator_process(tmp_path):
    # what is checked is the split path, not this shared machine's timing: a late TPDO only
    # counts as stale feedback here instead of ending the run (nor tripping the stale-share
    # safety limit); how well a loaded machine tracks is for benchmarks/realtime.py
    tolerant = {"master": {"stale_cycles": 100_000},
                "safety": {"stale_share_max": 1.0, "following_error_deg": 3600}}
    kpis, data = run(tmp_path, "rt", controller="mpc", reference="sine:amplitude=2,frequency=1",
                     duration_s=0.3, realtime=True, drive_overrides=tolerant)
    feedback = data.arrays("/drive/feedback")
    ticks = kpis["ticks"]
    assert kpis["clock"] == "realtime" and ticks > 0 and feedback["cycle"].size == ticks
    # the clock starts once the drive's first feedback is back (a cycle before tick 0, which
    # reads it); each later tick reads the TPDOs of the previous tick's SYNC
    cycles = feedback["cycle"]
    assert cycles[0] == 1 and feedback["fresh"][0] and feedback["rtt_us"][0] > 0
    assert np.all(np.diff(cycles) == 1)
    assert int(np.sum(~feedback["fresh"])) == kpis["stale_feedback"] < ticks
    process = next(m for _, m in data.topic("/events") if m["kind"] == "emulator.process")
    assert process["data"]["url"].startswith("socketcand://127.0.0.1:")  # not this process
    assert data.topic_counts["/mpc/prediction"] <= math.ceil(600 / 10)  # decimated


# --------------------------------------------------------------------- socketcand emulator
def test_lockstep_run_over_socketcand_matches_the_in_process_drive(tmp_path, capsys):
    # generous watchdogs: a loaded box may stall the lockstep loop for a moment
    config = tmp_path / "drive.toml"
    config.write_text("[master]\nheartbeat_timeout_ms = 5000\nrx_timeout_us = 2000000\n"
                      "[emulator]\nsync_loss_timeout_ms = 5000\n")
    proc, port = start_drive_emulator(config)
    try:
        out = tmp_path / "remote.mcap"
        assert main(["servo", "run", "--controller", "mpc", "--drive",
                     f"socketcand://127.0.0.1:{port}", "--config", str(config), "--reference",
                     "sine:amplitude=2,frequency=1", "--duration", "0.25", "--out", str(out),
                     "--json"]) == 0
        remote = json.loads(capsys.readouterr().out)
    finally:
        stop_drive_emulator(proc)
    assert remote["ticks"] == 500 and remote["stale_feedback"] == 0
    local, _ = run(tmp_path, "local", controller="mpc", reference="sine:amplitude=2,frequency=1",
                   duration_s=0.25)
    far = read_session(out).arrays("/drive/feedback")["position_deg"]
    near = read_session(local["mcap"]).arrays("/drive/feedback")["position_deg"]
    np.testing.assert_array_equal(far, near)  # the plant moves on SYNC: same run, bit for bit
    assert remote["max_error_deg"] == local["max_error_deg"] < 0.1


def test_servo_demo_writes_sessions_and_plots_and_mpc_beats_pid(tmp_path):
    from hil.servo.demo import run_servo_demo

    printed = []
    rows = run_servo_demo(tmp_path, echo=printed.append)
    assert [(r["frequency_hz"], r["umax_mA"], r["controller"]) for r in rows] == [
        (1.0, 1000.0, "mpc"), (1.0, 1000.0, "pid"), (10.0, 12000.0, "mpc"),
        (10.0, 12000.0, "pid")]
    for row in rows:
        assert Path(row["mcap"]).is_file() and Path(row["png"]).stat().st_size > 20_000
        assert row["peak_current_mA"] <= row["umax_mA"]
    for mpc, pid in (rows[0:2], rows[2:4]):
        assert mpc["max_error_deg"] < pid["max_error_deg"]
        assert mpc["cumulative_error_deg"] < pid["cumulative_error_deg"]
    assert len(printed) == 1 and "10 Hz, 12000 mA" in printed[0]
