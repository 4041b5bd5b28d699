"""The emulated drive in every mode of the table besides CST and CSP: CSV, PP, PV and HM (each
homing method on the simulated switches and index pulse), driven by SDO and SYNC frames on
the lockstep drive's bus. Each ends where CiA 402 says; each profile stays within the speed
and acceleration it is given. Positions and speeds are the drive's increments (2^20 a turn)."""

from __future__ import annotations

import itertools
import struct

import pytest

from hil.emulators.drive.modes import MOTIONS
from hil.emulators.drive.switches import Switches
from hil.protocols.cia402 import HOMING_METHODS, OPERATION_MODES
from tests.emulators.drive.test_node import Wire, abort_code, enable

TURN = 1 << 20
CYCLE_S = 0.0005
TR, ACK, ERR = 0x0400, 0x1000, 0x2000  # statusword bits 10, 12, 13


def counts(deg: float) -> int:
    return round(deg / 360.0 * TURN)


def signed(value: int) -> int:
    return value - (1 << 32) if value & 0x8000_0000 else value


class Drive(Wire):
    """The lockstep drive with a cycle of 1 ms, enabled in ``mode`` (a name of the table)."""

    def __init__(self, mode: str, **config) -> None:
        super().__init__(**config)
        self.write(0x1006, 0, int(CYCLE_S * 1e6), "<I")
        enable(self, OPERATION_MODES[mode].code)

    def value(self, index: int, sub: int = 0) -> int:
        """What the TPDOs of the last SYNC carried (the node's live value)."""
        return self.node.objects.values[(index, sub)]

    def cycles(self, n: int) -> list[dict[str, int]]:
        """``n`` SYNCs; after each, the statusword, position, velocity and their demands."""
        seen = []
        for _ in range(n):
            self.drive.sleep(CYCLE_S)
            seen.append({"sw": self.value(0x6041), "position": self.value(0x6064),
                         "velocity": self.value(0x606C), "demand": self.value(0x6062),
                         "demand_velocity": self.value(0x606B), "inputs": self.value(0x60FD)})
        self.collect()
        return seen

    def until(self, bits: int, limit_s: float, mask: int | None = None) -> list[dict[str, int]]:
        """SYNCs until the statusword has ``bits`` (of ``mask``), at most ``limit_s``."""
        mask = bits if mask is None else mask
        seen: list[dict[str, int]] = []
        while not seen or seen[-1]["sw"] & mask != bits:
            assert len(seen) * CYCLE_S < limit_s, f"statusword 0x{seen[-1]['sw']:04X}"
            seen += self.cycles(10)
        return seen

    def control(self, word: int) -> None:
        assert self.write(0x6040, 0, word, "<H")[0] == 0x60


@pytest.fixture
def drives():
    made: list[Drive] = []

    def make(mode: str, **config) -> Drive:
        made.append(Drive(mode, **config))
        return made[-1]
    yield make
    for drive in made:
        drive.close()


def within_profile(seen: list[dict[str, int]], speed: int, acceleration: int) -> None:
    """The demand never faster than ``speed`` nor changing faster than ``acceleration``;
    the axis' own velocity (which rings where the ramp ends) within 10 % of the speed."""
    demand = [s["demand_velocity"] for s in seen]
    assert max(map(abs, demand)) <= speed
    steps = [abs(b - a) / CYCLE_S for a, b in itertools.pairwise(demand)]
    assert max(steps) <= acceleration + 1 / CYCLE_S  # + the rounding to a count
    assert max(abs(s["velocity"]) for s in seen) <= speed * 1.1


def test_every_mode_of_the_table_has_its_motion():
    assert set(MOTIONS) == set(OPERATION_MODES)


def test_0x6502_lists_every_mode_of_the_table_and_each_is_taken(drives):
    drive = drives("csv")
    listed = struct.unpack_from("<I", drive.read(0x6502), 4)[0]
    for mode in OPERATION_MODES.values():
        assert listed & mode.supported_bit, mode.name
        assert drive.write(0x6060, 0, mode.code, "<b")[0] == 0x60
        assert drive.value(0x6061) == mode.code


def test_csv_follows_the_target_velocity_every_sync(drives):
    drive = drives("csv")
    drive.write(0x60FF, 0, counts(90), "<i")
    seen = drive.cycles(400)
    assert abs(seen[-1]["velocity"] - counts(90)) < counts(0.5)
    assert seen[-1]["sw"] & ACK  # bit 12: follows the command


def test_pp_moves_on_the_handshake_and_ends_within_the_position_window(drives):
    drive = drives("pp")
    speed, acceleration = counts(120), counts(600)
    drive.write(0x6081, 0, speed, "<I")
    drive.write(0x6083, 0, acceleration, "<I")
    drive.write(0x6084, 0, acceleration, "<I")
    drive.write(0x607A, 0, counts(150), "<i")
    drive.control(0x001F)  # new set point: rising edge of bit 4
    assert drive.statusword() & ACK  # taken at once (SDO: before any SYNC)
    seen = drive.cycles(20)
    assert not seen[-1]["sw"] & TR  # under way
    drive.control(0x000F)
    assert not drive.statusword() & ACK  # the handshake's end
    seen += drive.until(TR, 5.0)
    window = struct.unpack_from("<I", drive.read(0x6067), 4)[0]
    assert abs(seen[-1]["position"] - counts(150)) <= window
    assert not any(s["sw"] & ERR for s in seen)  # within the following error window
    within_profile(seen, speed, acceleration)
    # relative to the last target, past a whole turn: 0x6064 carries it modulo one turn
    drive.write(0x607A, 0, counts(300), "<i")
    drive.control(0x005F)
    drive.control(0x004F)
    seen = drive.until(TR, 5.0)
    assert abs(seen[-1]["position"] - counts(450 - 360)) <= window
    assert abs(signed(seen[-1]["demand"]) - counts(450)) <= 1


def test_pp_halt_stands_and_the_move_goes_on_when_it_falls(drives):
    drive = drives("pp")
    drive.write(0x607A, 0, counts(90), "<i")
    drive.control(0x001F)
    drive.cycles(300)
    drive.control(0x011F)  # halt
    seen = drive.until(TR, 2.0)
    assert abs(seen[-1]["velocity"]) < counts(2)
    stood = seen[-1]["position"]
    assert counts(5) < stood < counts(85)
    drive.control(0x001F)
    seen = drive.until(TR, 5.0)
    assert abs(seen[-1]["position"] - counts(90)) <= counts(0.1)


def test_pp_change_set_immediately_replaces_the_move_under_way(drives):
    drive = drives("pp")
    drive.write(0x607A, 0, counts(180), "<i")
    drive.control(0x001F)
    drive.control(0x000F)
    drive.cycles(300)
    drive.write(0x607A, 0, counts(20), "<i")
    drive.control(0x003F)  # bit 5: at once
    seen = drive.until(TR, 5.0)
    assert abs(seen[-1]["position"] - counts(20)) <= counts(0.1)
    assert max(s["position"] for s in seen) < counts(180)


def test_pp_sets_the_following_error_bit_beyond_its_window(drives):
    drive = drives("pp")
    drive.write(0x6065, 0, counts(0.01), "<I")
    drive.write(0x607A, 0, counts(90), "<i")
    drive.control(0x001F)
    seen = drive.cycles(200)
    assert any(s["sw"] & ERR for s in seen)


def test_pv_ramps_to_the_target_velocity_and_halts_to_speed_zero(drives):
    drive = drives("pv")
    acceleration = counts(300)
    drive.write(0x6083, 0, acceleration, "<I")
    drive.write(0x6084, 0, acceleration, "<I")
    assert drive.cycles(1)[-1]["sw"] & ACK  # speed zero
    drive.write(0x60FF, 0, counts(-60), "<i")
    seen = drive.until(TR, 2.0)
    assert abs(seen[-1]["velocity"] - counts(-60)) <= counts(2)  # 0x606D: 2 deg/s
    assert not seen[-1]["sw"] & ACK
    within_profile(seen, counts(60), acceleration)
    ramp_s = len([s for s in seen if abs(s["demand_velocity"]) < counts(60)]) * CYCLE_S
    assert ramp_s >= 60 / 300 * 0.99  # no faster than 0x6083
    drive.control(0x010F)  # halt
    seen = drive.until(TR | ACK, 2.0)
    assert abs(seen[-1]["velocity"]) <= counts(2)


#: where each method's home is, in degrees from power-on, with the default switches: limit
#: switches at -190 and 190 deg, the index pulse at 180 deg (and -180)
HOMES = {1: -180.0, 2: 180.0, 17: -190.0, 18: 190.0, 33: -180.0, 34: 180.0, 35: 0.0, 37: 0.0}
HOME_OFFSET = 12_345


def start_homing(drive: Drive, method: int) -> None:
    """Method ``method`` started, the zero search at 40 deg/s (the index is far away)."""
    drive.write(0x6098, 0, method, "<b")
    drive.write(0x6099, 2, counts(40), "<I")
    drive.write(0x607C, 0, HOME_OFFSET, "<i")
    drive.control(0x001F)


@pytest.mark.parametrize("method", sorted(HOMING_METHODS))
def test_each_homing_method_ends_at_its_home_reading_the_home_offset(drives, method):
    assert sorted(HOMES) == sorted(HOMING_METHODS)
    drive = drives("hm")
    start_homing(drive, method)
    seen = drive.until(TR | ACK, 12.0, TR | ACK | ERR)
    window = struct.unpack_from("<I", drive.read(0x6067), 4)[0]
    assert abs(seen[-1]["position"] - HOME_OFFSET) <= window
    assert abs(drive.node.plant.position_deg - HOMES[method]) <= window * 360 / TURN
    drive.cycles(200)  # and it stays there, holding its home
    assert abs(drive.value(0x6064) - HOME_OFFSET) <= counts(0.01)
    speed = struct.unpack_from("<I", drive.read(0x6099, 1), 4)[0]
    within_profile(seen, speed, struct.unpack_from("<I", drive.read(0x609A), 4)[0])
    switch = HOMING_METHODS[method].switch
    if switch:  # 0x60FD showed the switch it found
        assert any(s["inputs"] & switch for s in seen)


def test_0x60fd_reflects_the_limit_and_home_switches(drives):
    drive = drives("csv")
    assert drive.value(0x60FD) == 0
    drive.write(0x60FF, 0, counts(360), "<i")
    seen = drive.cycles(1400)
    inputs = [s["inputs"] for s in seen]
    assert 0x4 in inputs and 0x6 in inputs  # home switch from 90 deg, then + positive limit
    assert inputs.index(0x4) < inputs.index(0x6)


NARROW = Switches(negative_limit_deg=-100.0, positive_limit_deg=100.0, index_pulse_deg=150.0)


@pytest.mark.parametrize("switches, search_deg, method, why", [
    (Switches(negative_limit_deg=-5000.0), 360.0, 17, "never found"),
    (NARROW, 720.0, 33, "a limit before the index pulse"),
    (NARROW, 720.0, 2, "the other limit before the index pulse"),
], ids=lambda item: item if isinstance(item, str) else None)
def test_a_homing_that_cannot_end_sets_the_error_bit_and_stops(drives, switches, search_deg,
                                                               method, why):
    drive = drives("hm", switches=switches, homing_search_deg=search_deg)
    start_homing(drive, method)
    seen = drive.until(ERR | TR, 30.0, ERR | TR | ACK)
    assert abs(seen[-1]["velocity"]) < counts(2), why
    assert -5000 < drive.node.plant.position_deg < 5000


def test_a_homing_method_hil_does_not_emulate_is_refused(drives):
    drive = drives("hm")
    assert abort_code(drive.write(0x6098, 0, 3, "<b")) == 0x06090030
