"""Drive faults injected by the emulated CiA 402 node, seen by the master over socketcand on a
real TCP socket (127.0.0.1), and the master's reactions.

The node and its socketcand server run in this process (a thread) so each test starts in
milliseconds; the wire between master and node is python-can's stock socketcand client
talking TCP to the server. Fault times count from the node's creation (wall clock): each
fault starts ``AFTER_S`` later, once the master has enabled the drive.
"""

from __future__ import annotations

import time
from dataclasses import replace

import pytest

from hil.drivers.canopen import DriveFaultError, DriveLinkLostError
from hil.emulators.drive.node import DriveNode
from hil.emulators.faults import parse_fault
from hil.emulators.socketcand_server import SocketcandServer
from hil.protocols.cia402 import FAULT, OPERATION_ENABLED, state_of
from hil.servo.config import load_drive_config
from hil.servo.rig import open_drive

pytestmark = [pytest.mark.timeout(60), pytest.mark.slow]
AFTER_S = 1.0
# a TPDO wait of 5 ms after each SYNC and relaxed watchdogs on both sides (the drive's of the
# master, the master's of the drive's heartbeat: 3 x 300 ms): on a loaded machine only the
# injected fault trips them (a stall of this process once kept the emulator's heartbeat 318 ms
# apart, past 3 x the default 100 ms)
MASTER = {"stale_cycles": 20, "rx_timeout_us": 5000, "heartbeat_timeout_ms": 1000,
          "drive_heartbeat_ms": 300}
EMULATOR = {"sync_loss_timeout_ms": 300}


class Drive:
    """The emulated node behind a socketcand server, and a master connected to it."""

    def __init__(self, *faults: str) -> None:
        config = load_drive_config(overrides={"emulator": EMULATOR})
        self.server = SocketcandServer("127.0.0.1", 0, channel=config.emulator.channel)
        self.node = DriveNode(config.emulator, send=self.server.broadcast,
                              faults=[parse_fault(f) for f in faults])
        self.server.on_frame, self.server.on_tick = self.node.handle, self.node.service
        self.node.boot()
        self.server.start()
        self.events: list[tuple[str, str]] = []
        host, port = self.server.address
        master_config = load_drive_config(overrides={"master": MASTER})
        self.master = open_drive(f"socketcand://{host}:{port}", master_config,
                                 on_event=lambda kind, message, **_: self.events.append(
                                     (kind, message)))
        self.master.start()

    def run_until_error(self, limit_s: float = 5.0) -> Exception:
        """Cycle at ~1 kHz (zero current) until the master raises; return what it raised."""
        deadline = time.monotonic() + limit_s
        while time.monotonic() < deadline:
            try:
                self.master.exchange(0.0)
            except Exception as exc:  # the reaction under test
                return exc
            time.sleep(0.001)
        raise AssertionError(f"no reaction within {limit_s} s; events {self.events}")

    def run_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.master.exchange(0.0)
            time.sleep(0.001)

    def kinds(self) -> list[str]:
        return [kind for kind, _ in self.events]

    def close(self) -> None:
        self.master.disconnect()
        self.server.close()


@pytest.fixture
def drive(request):
    made: list[Drive] = []

    def make(*faults: str) -> Drive:
        made.append(Drive(*faults))
        return made[-1]

    yield make
    for d in made:
        d.close()


def test_a_silent_drive_is_a_lost_link(drive):
    d = drive(f"silent@{AFTER_S}")
    error = d.run_until_error()
    assert isinstance(error, DriveLinkLostError)
    assert "no TPDO for 20 cycles" in str(error) or "no heartbeat for" in str(error)
    assert "drive.link_lost" in d.kinds()
    assert d.node.faults.events[0]["fault"] == f"silent@{AFTER_S:g}"


def test_dropped_tpdos_are_stale_cycles_and_all_dropped_a_lost_link(drive):
    d = drive(f"drop_tpdo@{AFTER_S}-{AFTER_S + 0.3}:every=3", f"drop_tpdo@{AFTER_S + 0.5}")
    d.run_for(AFTER_S + 0.4 - d.node.faults.now())
    stale = d.master.stats.stale
    assert stale > 0 and d.master.link_up  # every third: stale cycles, no loss
    error = d.run_until_error()
    assert isinstance(error, DriveLinkLostError) and "no TPDO" in str(error)


def test_late_tpdos_are_stale_cycles_and_very_late_ones_a_lost_link(drive):
    # 20 ms late: the first cycles of the window miss their 5 ms wait (stale), then the late
    # TPDOs stream in and look fresh (CANopen TPDOs carry no counter): counted, not fatal
    d = drive(f"delay_tpdo@{AFTER_S}-{AFTER_S + 0.4}:ms=20", f"delay_tpdo@{AFTER_S + 0.6}:ms=400")
    d.run_for(AFTER_S + 0.5 - d.node.faults.now())
    assert d.master.stats.stale > 0 and d.master.link_up
    # 400 ms late: more than stale_cycles (20) cycles without a TPDO
    error = d.run_until_error()
    assert isinstance(error, DriveLinkLostError) and "no TPDO for 20 cycles" in str(error)


def test_a_stopped_heartbeat_is_a_lost_link(drive):
    d = drive(f"no_heartbeat@{AFTER_S}")
    error = d.run_until_error()
    assert isinstance(error, DriveLinkLostError) and "no heartbeat for" in str(error)
    assert d.node.faults.now() >= AFTER_S + 0.6  # 3 periods after the last heartbeat


@pytest.mark.parametrize("code", [0x2310, 0x4310])
def test_an_emcy_fault_stops_the_drive_with_its_code(drive, code):
    d = drive(f"emcy@{AFTER_S}:code={code:#06x}")
    error = d.run_until_error()
    assert isinstance(error, DriveFaultError) and error.emcy_code == code
    assert "drive.emcy" in d.kinds() and "drive.fault" in d.kinds()
    assert f"0x{code:04X}" in str(error)


def test_an_ignored_controlword_is_caught_and_the_sync_watchdog_faults_the_drive(drive):
    d = drive(f"ignore_controlword@{AFTER_S}")
    d.run_for(AFTER_S + 0.1 - d.node.faults.now())
    d.master.config = replace(d.master.config, quick_stop_timeout_s=0.2)
    d.master.safe_state()
    assert "drive.safe_stop_failed" in d.kinds()
    time.sleep(0.6)  # no SYNC any more: the drive's SYNC watchdog (300 ms) faults it
    assert state_of(d.master.sdo.read_int(0x6041, 0, "<H")) == FAULT
    assert d.node.state != OPERATION_ENABLED
