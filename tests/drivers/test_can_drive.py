"""The CiA 402 master against the emulated drive (lockstep on a python-can virtual bus):
configuration by SDO, physics through CAN, clamp, unwrapping, watchdogs, faults, EMCY events,
safe stop, explicit recovery, and a drive that will not leave its state (canopen LocalNode)."""

import math
import re
import struct
import time
import uuid
from collections.abc import Callable

import can
import canopen
import pytest

from hil.contracts import no_event
from hil.core.clock import SimClock
from hil.core.loop import FunctionTask
from hil.core.recording.reader import read_session
from hil.core.session import Session
from hil.drivers.canopen import (
    BusSharedError,
    DriveError,
    DriveFaultError,
    DriveLinkLostError,
    DriveStateError,
    SdoAbortError,
)
from hil.emulators.drive.od import build_object_dictionary
from hil.errors import ConfigError
from hil.protocols.cia402 import RPDOS, TPDOS
from hil.servo.config import load_drive_config
from hil.servo.rig import open_drive


class Events:
    """An on_event sink with the signature of Session.event."""

    def __init__(self):
        self.items = []

    def __call__(self, kind, message, level="info", source="", **data):
        self.items.append((kind, level, message, data))

    def kinds(self):
        return [kind for kind, *_ in self.items]


def emulated(overrides=None, events=None):
    return open_drive("emulated", load_drive_config(overrides=overrides),
                      on_event=events or no_event)


def controlwords(frames, node_id=1):
    return [struct.unpack_from("<H", m.data)[0] for m in frames
            if m.arbitration_id == 0x200 + node_id]


def drain(bus):
    frames = []
    while (msg := bus.recv(0)) is not None:
        frames.append(msg)
    return frames


def test_start_configures_the_drive_by_sdo():
    events = Events()
    master = emulated({"master": {"current_limit_mA": 750.0, "drive_heartbeat_ms": 20}}, events)
    feedback = master.start()
    assert feedback.state == "OPERATION ENABLED" and feedback.position_deg == 0.0
    read = master.sdo.read_int
    for pdo in (*RPDOS, *TPDOS):
        assert read(pdo.mapping, 0, "<B") == 2
        assert [read(pdo.mapping, sub) for sub in (1, 2)] == pdo.mapping_values()
    assert read(0x1006) == 500
    assert read(0x1017, 0, "<H") == 20
    assert read(0x1016, 1) == (127 << 16) | 300
    assert read(0x6061, 0, "<b") == 10
    assert read(0x6072, 0, "<H") == 750
    assert read(0x605A, 0, "<h") == 2
    assert events.kinds()[:3] == ["drive.current_limit", "drive.configured", "drive.enabled"]
    assert events.items[0][3] == {"applied_mA": 750.0, "run_mA": 750.0,
                                  "drive_max_current_mA": None, "drive_max_torque_mA": 1000.0}
    assert events.items[1][3]["bus_budget"]["fits"] is True
    master.close()


def test_constant_current_through_can_gives_the_model_acceleration():
    master = emulated()
    master.start()
    for _ in range(2000):  # 1 s at 100 mA
        feedback = master.exchange(100.0)
    assert feedback.fresh and feedback.cycle == 2000
    assert feedback.t_ns == 1_000_000_000
    acceleration_per_ma = 2.0 * feedback.position_deg / 1.0**2 / 100.0
    assert acceleration_per_ma == pytest.approx(2.83, rel=0.01)
    assert feedback.velocity_deg_s == pytest.approx(283.0, rel=0.02)
    assert feedback.current_ma == 100.0 and feedback.command_ma == 100.0
    master.close()


@pytest.mark.parametrize("current", [1000.0, -1000.0])
def test_multi_turn_position_is_unwrapped_by_the_master(current):
    master = emulated()
    master.start()
    plant = master.emulator.node.plant
    for _ in range(3000):  # 1.5 s at the limit: about 3200 deg, nine turns
        feedback = master.exchange(current)
        assert 0 <= feedback.position_increments < master.increments_per_rev
    assert abs(feedback.position_deg) > 3000.0
    assert math.copysign(1, feedback.position_deg) == math.copysign(1, current)
    assert feedback.position_deg == pytest.approx(plant.position_deg, abs=360 / 2**20)
    master.close()


def test_commands_are_clamped_to_the_current_limit_in_the_driver():
    master = emulated({"master": {"current_limit_mA": 400.0}})
    master.start()
    feedback = master.exchange(5000.0)
    assert feedback.command_ma == 400.0 and feedback.current_ma == 400.0
    assert master.emulator.node.plant.applied_current_ma == 400.0
    feedback = master.exchange(-1e9)
    assert feedback.command_ma == -400.0
    assert master.stats.clamped_commands == 2
    with pytest.raises(DriveError, match="non-finite"):
        master.exchange(float("nan"))
    master.close()


def test_split_exchange_gives_the_same_trajectory_as_exchange():
    one, two = emulated(), emulated()
    one.start()
    assert two.start() == two.receive_feedback()  # nothing sent yet: the start feedback
    for k in range(300):
        current = 300.0 * math.sin(k / 20)
        a = one.exchange(current)
        two.send_command(current)
        b = two.receive_feedback()
        assert a.position_deg == b.position_deg
    one.close()
    two.close()


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_safe_state_quick_stops_then_disables_and_is_idempotent():
    events = Events()
    master = emulated(events=events)
    master.start()
    observer = master.emulator.attach_bus()
    for _ in range(400):
        master.exchange(800.0)
    drain(observer)
    master.safe_state()
    words = controlwords(drain(observer))
    assert words[0] == 0x0002 and words[-1] == 0x0000  # quick stop ... then disable voltage
    assert set(words) == {0x0002, 0x0000}
    node = master.emulator.node
    assert node.state == "SWITCH ON DISABLED"
    assert abs(node.plant.velocity_deg_s) < 5.0  # it braked from ~1100 deg/s, not coasted
    assert events.kinds()[-1] == "drive.safe_stop"
    master.safe_state()
    assert drain(observer) == []
    with pytest.raises(DriveStateError, match="not enabled"):
        master.exchange(0.0)
    observer.shutdown()
    master.close()


def test_link_lost_when_tpdos_stop_latches_until_recover():
    events = Events()
    master = emulated({"master": {"stale_cycles": 5}}, events)
    master.start()
    for _ in range(10):
        master.exchange(0.0)
    # the node stops on its own (handed an NMT stop directly: on the bus, an NMT command the
    # master did not send would be another master, which stops the run for that reason)
    master.emulator.node.handle_frame(0x000, bytes([0x02, 1]))
    stale = []
    with pytest.raises(DriveLinkLostError, match="no TPDO for 5 cycles"):
        for _ in range(10):
            stale.append(master.exchange(0.0))
    assert len(stale) == 4 and not any(f.fresh for f in stale)
    assert "drive.link_lost" in events.kinds()
    assert not master.link_up and master.watchdog.losses == 1
    assert master.stats.longest_stale_run == master.watchdog.longest_run == 5
    with pytest.raises(DriveLinkLostError, match="latched: call recover"):
        master.exchange(0.0)
    feedback = master.recover()  # NMT pre-op (the node was STOPPED), fault reset, enable
    assert feedback.state == "OPERATION ENABLED" and master.link_up
    assert master.exchange(10.0).fresh
    master.close()


def test_drive_reboot_is_a_lost_link_and_needs_an_explicit_recovery():
    events = Events()
    master = emulated(events=events)
    master.start()
    master.exchange(0.0)
    master.emulator.node.handle_frame(0x000, bytes([0x81, 1]))  # the node resets on its own
    with pytest.raises(DriveLinkLostError, match="restarted"):
        master.exchange(0.0)
    assert "drive.bootup" in events.kinds() and not master.link_up
    with pytest.raises(DriveLinkLostError):
        master.exchange(0.0)
    assert master.recover().state == "OPERATION ENABLED"
    assert master.exchange(0.0).fresh
    master.close()


def test_heartbeat_loss_faults_the_drive_and_the_master_reports_the_emcy():
    events = Events()
    # the master beats every second but the drive gives up after 20 ms of silence
    master = emulated({"master": {"heartbeat_period_ms": 1000, "heartbeat_timeout_ms": 20}},
                      events)
    master.start()
    assert ("drive.heartbeat_config", "warning") in [item[:2] for item in events.items]
    with pytest.raises(DriveFaultError, match="0x8130") as error:
        for _ in range(100):
            master.exchange(0.0)
    assert error.value.emcy_code == 0x8130
    # heartbeat stamped at the first SYNC (0.5 ms); silent for more than 20 ms at SYNC 42
    # (21 ms): the fault shows in the TPDO of the next SYNC; then its safe stop, a quick stop
    # cycle (FAULT stands) and a disable voltage cycle
    assert master.feedback.cycle == 45
    assert events.kinds()[-2:] == ["drive.fault", "drive.safe_stop"]
    emcy = [item for item in events.items if item[0] == "drive.emcy"]
    assert emcy[0][1] == "error" and emcy[0][3]["code"] == 0x8130
    assert "drive.fault" in events.kinds()
    with pytest.raises(DriveFaultError, match="latched") as again:
        master.exchange(0.0)
    assert again.value.emcy_code == 0x8130
    assert master.recover().state == "OPERATION ENABLED"
    assert "drive.fault_reset" in events.kinds()
    master.close()


def test_start_refuses_a_drive_in_fault_until_recover():
    master = emulated({"master": {"current_limit_mA": 20000.0},
                       "emulator": {"max_torque_permille": 20000}})
    master.start()
    with pytest.raises(DriveFaultError):
        for _ in range(50):
            master.exchange(16000.0)  # beyond the 15 A trip level of the emulator
    master2 = open_drive("emulated")  # a second master, another emulator: unaffected
    master2.close()
    with pytest.raises(DriveFaultError, match=r"0x2310.*hil drive reset"):
        master.start()
    assert master.recover().state == "OPERATION ENABLED"
    master.close()


def test_emcy_and_fault_are_recorded_as_session_events(tmp_path):
    path = tmp_path / "drive.mcap"
    session = Session(str(path), SimClock(), 500e-6, kind="servo", handle_signals=False)
    master = emulated({"master": {"current_limit_mA": 20000.0},
                       "emulator": {"max_torque_permille": 20000}}, session.event)
    master.start()
    session.add_component(master)
    currents = iter([100.0] * 20 + [16000.0] * 10)
    session.add_task(FunctionTask("drive", write=lambda _t: master.exchange(next(currents))))
    with pytest.raises(DriveFaultError):
        session.run(max_ticks=30)
    session.close()
    master.close()
    events = [message for _, message in read_session(str(path)).topic("/events")]
    kinds = [e["kind"] for e in events]
    assert kinds.index("drive.enabled") < kinds.index("drive.emcy") < kinds.index("drive.fault")
    emcy = events[kinds.index("drive.emcy")]
    assert emcy["level"] == "error" and emcy["data"]["code"] == 0x2310
    assert emcy["source"] == "drive1"


def test_csp_mode_tracks_a_position_target():
    master = emulated({"master": {"mode": "csp"}})
    master.start()
    assert master.sdo.read_int(0x1600, 2) == 0x607A0020
    worst = 0.0
    for k in range(4000):  # a smooth 1.5 s move of 400 deg (over a turn), then hold
        target = 200.0 * (1.0 - math.cos(math.pi * min(k * 500e-6, 1.5) / 1.5))
        feedback = master.exchange_position(target)
        worst = max(worst, abs(feedback.position_deg - target))
    assert worst < 1.0  # the drive's own loop with feed-forward follows closely
    assert feedback.position_deg == pytest.approx(400.0, abs=0.01)
    with pytest.raises(DriveStateError, match=r"send_command\(\) sends mA, and mode CSP takes "
                       "deg"):
        master.send_command(0.0)
    assert master.exchange(400.0).position_deg == pytest.approx(400.0, abs=0.01)  # the mode's
    master.close()


@pytest.mark.parametrize("mode", ["cst", "csp"])
def test_prime_is_one_cycle_that_holds_the_axis_where_it_stands(mode):
    master = emulated({"master": {"mode": mode}})
    master.start()
    for _ in range(400):  # under way: 50 mA, or a position target moving at 180 deg/s
        moved = master.exchange(50.0 if mode == "cst" else master.feedback.position_deg + 0.09)
    primed = master.prime()
    assert primed.fresh and primed.cycle == moved.cycle + 1
    if mode == "cst":
        assert primed.command_ma == 0.0  # no current
    else:  # its target is where the axis stood: the drive brakes towards it
        assert abs(primed.position_deg - moved.position_deg) < 0.09
    assert master.receive_feedback() == primed  # a loop's first read: the primed cycle's
    master.close()


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_a_drive_stuck_in_its_state_gives_an_error_naming_the_state():
    """A canopen LocalNode serving a 402 dictionary answers SDO but has no state machine."""
    channel = f"stuck-{uuid.uuid4().hex}"
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    od = build_object_dictionary(1)
    od[0x6041].default = 0x0250  # SWITCH ON DISABLED, forever
    local = canopen.LocalNode(1, od)
    network.add_node(local)

    def mirror_mode(index, subindex, od, data):
        if index == 0x6060:
            local.data_store.setdefault(0x6061, {})[0] = bytes(data)

    local.add_write_callback(mirror_mode)
    config = load_drive_config(overrides={"master": {"state_timeout_ms": 300}})
    master = open_drive(f"virtual://{channel}", config)
    try:
        with pytest.raises(DriveStateError, match=r"stuck in SWITCH ON DISABLED \(statusword "
                                                  r"0x0250\) waiting for READY TO SWITCH ON"):
            master.start()
    finally:
        master.close()
        network.disconnect()


def test_sdo_refusals_name_the_object_and_the_abort_code():
    master = emulated()
    with pytest.raises(SdoAbortError, match=r"0x6060:00 = 2.*0x06090030") as error:
        master.sdo.write(0x6060, 0, 2, "<b")  # VL: not a mode the emulator has
    assert error.value.code == 0x06090030
    assert master.sdo.read(0x1008).decode() == "hil CiA 402 drive emulator"  # segmented
    master.close()


@pytest.mark.parametrize(("where", "problem"), [
    ("nowhere", ConfigError), ("socketcand://127.0.0.1", ConfigError),
    ("socketcand://127.0.0.1:1", DriveLinkLostError),
])
def test_open_drive_rejects_bad_addresses_with_one_clear_error(where, problem):
    with pytest.raises(problem):
        open_drive(where)


def test_bad_master_config_values_are_config_errors():
    with pytest.raises(ConfigError, match=r"master\.mode"):
        load_drive_config(overrides={"master": {"mode": "velocity"}})
    with pytest.raises(ConfigError, match=r"unknown key 'master\.curent_limit_mA'"):
        load_drive_config(overrides={"master": {"curent_limit_mA": 10.0}})
    with pytest.raises(ConfigError, match=r"master\.current_limit_mA"):
        load_drive_config(overrides={"master": {"current_limit_mA": -1.0}})


def test_a_period_too_short_for_the_bus_is_warned_about():
    events = Events()
    master = emulated({"master": {"cycle_period_us": 250, "heartbeat_period_ms": 0}}, events)
    assert not master.budget.fits
    with pytest.raises(SdoAbortError):  # the emulated plant also refuses 250 us (T = 500 us)
        master.start()
    assert not [e for e in events.items if e[0] == "drive.bus_budget"]  # refused before
    master2 = emulated({"bus": {"bitrate": 500_000}}, events)
    master2.start()
    warnings = [e for e in events.items if e[0] == "drive.bus_budget"]
    assert warnings and warnings[0][1] == "warning" and "more than the 500 us period" in \
        warnings[0][2]
    master.close()
    master2.close()


@pytest.mark.parametrize(("cob_id", "data", "what"), [
    (0x000, [0x02, 1], "an NMT command (0x000)"),
    (0x080, [], "a SYNC (0x080)"),
    (0x77F, [0x05], "a heartbeat with this master's node id 127 (0x77F)"),
])
@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_another_master_on_the_bus_stops_the_exchange(cob_id, data, what):
    events = Events()
    master = emulated(events=events)
    master.start()
    other = master.emulator.attach_bus()  # a second master on the same bus
    try:
        master.exchange(0.0)
        with pytest.raises(BusSharedError, match=f"another master on .*: {re.escape(what)}"):
            for _ in range(3):
                other.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))
                master.exchange(0.0)
        assert "bus.foreign_master" in events.kinds()
    finally:
        other.shutdown()
        master.close()
    # the safe stop still went out (found by the fuzz campaign: the latched error stopped it);
    # the other master's NMT stop faulted the drive before it (it left OPERATIONAL enabled)
    assert master.emulator.node.state in ("SWITCH ON DISABLED", "FAULT")


def test_the_lockstep_drives_own_time_is_no_other_masters_sync():
    # found by the fuzz campaign (tests/fuzz): the SYNCs by which the emulated drive lets its
    # time pass (a master waiting for a state) reached the master, which stopped the run
    master = emulated()
    master.start()
    try:
        master.clock.sleep(0.01)  # 20 SYNCs of the drive's own
        assert master.exchange(0.0).state == "OPERATION ENABLED"
        assert master.foreign is None
    finally:
        master.close()


def test_a_drive_enabled_whose_answer_is_lost_is_disabled_again():
    # found by the fuzz campaign (tests/fuzz): the enable's last answer lost, the master
    # raised without ever counting the drive enabled, and close() left it enabled
    master = emulated({"master": {"sdo_timeout_ms": 20}})
    node, receive = master.emulator.node, master.link._recv_frame

    def lossy(timeout=None):  # every SDO answer given once the drive is enabled is lost
        frame = receive(timeout)
        if frame is not None and frame[0] == 0x581 and node.state == "OPERATION ENABLED":
            return None
        return frame

    master.link._recv_frame = lossy
    with pytest.raises(DriveLinkLostError, match="did not answer SDO"):
        master.start()
    master.close()
    assert node.state == "SWITCH ON DISABLED"


def test_a_tpdo_that_says_fault_still_stops_the_drive():
    # found by the fuzz campaign (benchmarks/fuzz.py): a TPDO1 damaged to statusword 0x000F
    # (FAULT REACTION ACTIVE) made the master drop the drive without a stop, and the drive,
    # enabled all along, stayed so
    master = emulated()
    master.start()
    receive, damaged = master.link._recv_frame, []

    def says_fault(timeout=None):
        frame = receive(timeout)
        if frame is not None and frame[0] == 0x181 and not damaged:
            damaged.append(frame)
            return 0x181, b"\x0f\x00" + frame[1][2:]
        return frame

    master.link._recv_frame = says_fault
    with pytest.raises(DriveFaultError, match="FAULT REACTION ACTIVE"):
        master.exchange(0.0)
    master.close()
    assert master.emulator.node.state == "SWITCH ON DISABLED"


def _hils_drive(url: str) -> tuple[int, Callable[[], None]]:
    """hil's emulated drive on the wall clock in a thread (patient with the master's silence)."""
    from hil.emulators.drive.config import DriveEmulatorConfig
    from hil.emulators.drive.node import DriveNode
    from hil.emulators.drive.runners import BusRunner, bus_sender

    node_bus = can.Bus(interface="virtual", channel=url.removeprefix("virtual://"))
    runner = BusRunner(DriveNode(DriveEmulatorConfig(sync_loss_timeout_ms=5000),
                                 send=bus_sender(node_bus)), node_bus).start()

    def stop() -> None:
        runner.stop()
        node_bus.shutdown()

    return 1, stop


def _independent_drive(url: str) -> tuple[int, Callable[[], None]]:
    """A CiA 402 slave hil did not write (canopen's LocalNode, its heartbeat canopen's)."""
    from tests.drive_slave import serve

    network, _ = serve(url, 3)
    return 3, network.disconnect


# no loop at a kHz: a 10 Hz heartbeat watched over 300 ms while this process sleeps 0.6 s (its
# GIL free), so with the rest of the suite
@pytest.mark.parametrize("drive", [_hils_drive, _independent_drive], ids=["hil", "independent"])
def test_a_held_up_master_reads_the_heartbeats_waiting_before_it_calls_the_drive_silent(drive):
    """The master's process held up for longer than the drive's heartbeat watch (a loaded
    machine, a slow writer in lockstep): the drive beat all along, its heartbeats wait behind
    the cycle's TPDOs, and the master reads them before it calls the drive silent. The drive
    beats on the wall clock (python-can virtual bus) and ignores the master's silence, so only
    the master's watch is tested."""
    url = f"virtual://held-up-{uuid.uuid4().hex}"
    node_id, stop = drive(url)
    config = load_drive_config(overrides={"master": {
        "node_id": node_id, "heartbeat_timeout_ms": 5000,
        "drive_heartbeat_ms": 100,  # watched for 300 ms
        "rx_timeout_us": 100_000, "stale_cycles": 1000}})
    master = open_drive(url, config)
    try:
        master.start()
        for _ in range(5):
            assert master.exchange(0.0).fresh
        master.send_command(0.0)  # the TPDOs come at once, the heartbeats behind them
        time.sleep(0.6)  # held up: twice the watch, the drive beating all along
        assert master.receive_feedback().fresh and master.link_up
        assert master.exchange(0.0).fresh
    finally:
        master.close()
        stop()


def test_the_heartbeat_watch_tells_the_silence_at_a_time_given_or_now():
    """The master asks for the silence at its feedback's time (its clock, read a moment
    before); asked without a time, the watch reads the clock itself."""
    from hil.drivers.canopen.nmt import HeartbeatWatch

    now = [1_000_000_000]
    watch = HeartbeatWatch(1, 100, lambda: now[0])  # silent past 300 ms
    watch.restart()
    assert watch.silent_ns(now[0] + 300_000_000) is None
    assert watch.silent_ns(now[0] + 300_000_001) == 300_000_001
    now[0] += 400_000_000
    assert watch.silent_ns() == 400_000_000
    assert HeartbeatWatch(1, 0, lambda: now[0]).silent_ns(now[0] + 10**12) is None  # unwatched


def test_a_drive_on_sync_time_is_watched_from_the_first_cycle_not_from_its_enabling():
    """A drive on the master's SYNC time (an emulator's clock "sync") beats only once SYNCs
    come: a master held up between enabling the drive and its first cycle for longer than its
    heartbeat watch (a run starting on a loaded machine) does not call the drive silent."""
    from tests.served_here import drive_served_here

    with drive_served_here(clock="sync") as drive:
        config = load_drive_config(overrides={"master": {
            "drive_heartbeat_ms": 100,   # watched for 300 ms of the master's (wall) time
            # a beat every 5 SYNCs of the drive's time: the exchanges below, as quick as the
            # machine allows, may each take up to 60 ms (a loaded machine) without a beat late
            "cycle_period_us": 20000,
            "heartbeat_timeout_ms": 5000, "stale_cycles": 1000}})
        master = open_drive(drive.url, config)
        try:
            master.start()
            time.sleep(0.5)  # held up past the watch, no SYNC sent: the drive's time stands
            for _ in range(30):  # 600 ms of the drive's time: its beats come, the link holds
                master.exchange(0.0)
            assert master.link_up
        finally:
            master.close()
