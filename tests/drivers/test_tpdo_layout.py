"""The one-TPDO layout (``[master] tpdo_layout = "one"``): statusword, position and torque in
one 8-byte TPDO, TPDO2 invalidated, the velocity derived by the master from the position;
against hil's emulator (which remaps its PDOs as CiA 301 says) and against a CiA 402 slave hil
did not write (canopen's LocalNode, tests/drive_slave.py) on a python-can virtual bus."""

from __future__ import annotations

import json
import uuid

import pytest

from hil.drivers.canopen import CanDriveMaster, CanLink, DriveMasterConfig
from hil.drivers.canopen.bus import open_can_bus, parse_can_url
from hil.drivers.canopen.bus_plan import axis_traffic
from hil.drivers.canopen.pdo import tpdo_maps, unused_pdos
from hil.emulators.drive.runners import LockstepDrive
from hil.protocols.cia402 import TPDO1, TPDO1_ALONE, TPDO2
from tests.cli import hil_here
from tests.drive_slave import CST, HM, INCREMENTS, dictionary, serve

ONE = DriveMasterConfig(tpdo_layout="one")


def test_the_layouts_map_what_feedback_needs_and_the_plan_counts_their_bytes():
    assert tpdo_maps(None) == (TPDO1, TPDO2)
    assert tpdo_maps(None, "one") == (TPDO1_ALONE,)
    assert TPDO1_ALONE.mapping_values() == [0x60410010, 0x60640020, 0x60770010]
    assert TPDO1_ALONE.size_bytes == 8
    assert axis_traffic(ONE).tpdo_bytes == (8,)
    assert axis_traffic(DriveMasterConfig()).tpdo_bytes == (6, 6)
    # TPDO2 is the master's no more: invalidated with TPDO3-4 and RPDO2-4
    assert 0x1801 in unused_pdos(tpdo_maps(None, "one"))
    assert 0x1801 not in unused_pdos(tpdo_maps(None))
    with pytest.raises(ValueError, match="no room for the sync_echo byte"):
        tpdo_maps((0x2004, 0), "one")
    with pytest.raises(ValueError, match="tpdo_layout must be one of two, one"):
        tpdo_maps(None, "three")


def test_hils_emulator_takes_the_remapping_and_the_master_derives_the_velocity():
    emulator = LockstepDrive()
    observer = emulator.attach_bus()
    master = CanDriveMaster(CanLink(emulator.master_bus), ONE, clock=emulator)
    master.start()
    while observer.recv_frame() is not None:
        pass  # the set-up's frames
    for _ in range(300):
        feedback = master.exchange(300.0)
    frames = []
    while (frame := observer.recv_frame()) is not None:
        frames.append(frame)
    plant = emulator.node.plant
    position, velocity = plant.position_deg, plant.velocity_deg_s  # before the stop's cycles
    master.close()
    emulator.close()
    tpdos = [(can_id, data) for can_id, data in frames if can_id in (0x181, 0x281, 0x381, 0x481)]
    assert {can_id for can_id, _ in tpdos} == {0x181}  # TPDO2 invalidated
    assert all(len(data) == 8 for _, data in tpdos)
    assert feedback.fresh and master.stats.stale == 0 and master.stats.malformed_frames == 0
    assert feedback.position_deg == pytest.approx(position, abs=360 / 2**20)
    assert feedback.current_ma == pytest.approx(300.0, abs=1.0)  # torque in the same TPDO
    # the position's change over one 500 us cycle: the plant's own velocity, to two counts
    assert velocity > 100.0
    assert feedback.velocity_deg_s == pytest.approx(velocity, abs=2 * 360 / 2**20 / 500e-6)


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_a_slave_hil_did_not_write_is_remapped_to_one_tpdo():
    url = f"virtual://layout-{uuid.uuid4().hex}"
    network, slave = serve(url, 3)
    # a thread answers here, not a drive: a patient deadline (what is tested is the mapping)
    config = DriveMasterConfig(node_id=3, tpdo_layout="one", rx_timeout_s=0.05,
                               stale_cycles=1000)
    master = CanDriveMaster(CanLink(open_can_bus(parse_can_url(url))), config)
    try:
        master.start()
        for _ in range(100):
            feedback = master.exchange(100.0)
        velocity, position = slave.velocity, slave.position
        mapping = [slave.value(0x1A00, sub) for sub in range(slave.value(0x1A00, 0) + 1)]
        tpdo2 = slave.value(0x1801, 1)
        logged = slave.log[-1]
    finally:
        master.close()
        network.disconnect()
    assert mapping == [3, 0x60410010, 0x60640020, 0x60770010]
    assert tpdo2 & 0x8000_0000 and logged["tpdo2"] is None  # invalid: never sent
    assert len(bytes.fromhex(logged["tpdo1"])) == 8
    # a thread on a busy machine may answer a cycle past the 50 ms: that cycle is then stale
    # and its answer counted late, never taken for fresh (the wall clock, not the mapping)
    assert feedback.fresh and master.stats.stale == master.stats.late_frames
    assert master.stats.malformed_frames == 0
    assert feedback.position_deg == pytest.approx(position, abs=360 / INCREMENTS)
    # the slave moves 500 us per SYNC: its velocity is the position's change per cycle
    assert velocity > 1000.0
    assert feedback.velocity_deg_s == pytest.approx(velocity, abs=2 * 360 / INCREMENTS / 500e-6)


@pytest.mark.parametrize("method", [17, 34, 37])
def test_a_homing_with_one_tpdo_is_no_runaway_at_its_new_zero(tmp_path, capsys, method):
    """The velocity is derived from the position: the feedback in which the drive says homing
    attained already holds the position in its new frame (a jump of up to a turn in one
    cycle), which is not a speed. The homing ends at home, the axis' peak speed that of the
    search, and [safety] velocity_max_deg_s still holds."""
    (tmp_path / "one.toml").write_text('[master]\ntpdo_layout = "one"\n')
    homed = hil_here(capsys, "drive", "home", "emulated", "--config", "one.toml", "--method",
                     method, "--speed", 90, "--zero-speed", 45, "--json", "--out", "h.mcap",
                     cwd=tmp_path)
    assert homed.returncode == 0, homed.stderr
    kpis = json.loads(homed.stdout)
    assert kpis["reached"] and kpis["status"] == "completed"
    assert abs(kpis["position_deg"]) < 0.5
    assert kpis["peak_velocity_deg_s"] < 120.0, kpis


@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_a_homing_on_a_slave_hil_did_not_write_is_no_runaway_with_one_tpdo(tmp_path, capsys):
    """canopen's LocalNode (tests/drive_slave.py) homes by method 37 where it stands: its
    position jumps from 120 deg to the home offset (0) in the cycle its statusword says homing
    attained. With the velocity derived from the position, that jump is no speed: the homing
    ends at home, the axis never moved."""
    url = f"virtual://layout-{uuid.uuid4().hex}"
    network, slave = serve(url, 3, od=dictionary(3, modes=(CST, HM)))
    slave.position = 120.0
    # a thread answers here, not a drive: a patient deadline (what is tested is the homing)
    (tmp_path / "one.toml").write_text('[master]\ntpdo_layout = "one"\nmode = "hm"\n'
                                       'rx_timeout_us = 50000\nstale_cycles = 1000\n')
    try:
        homed = hil_here(capsys, "drive", "home", url, "--node", 3, "--config", "one.toml",
                         "--method", 37, "--json", "--out", "h.mcap", cwd=tmp_path)
    finally:
        network.disconnect()
    assert homed.returncode == 0, homed.stderr
    kpis = json.loads(homed.stdout)
    assert kpis["reached"] and abs(kpis["position_deg"]) < 0.5, kpis
    assert kpis["peak_velocity_deg_s"] < 1.0, kpis
