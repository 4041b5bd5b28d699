"""The vendor files of tests/data/drives (tests/data/drives/README.md) as twins: each that lists
a mode hil emulates is twinned with the values its vendor leaves for commissioning supplied
(``set``, as ``--set`` and ``[emulator] set`` give them), and driven by SDO and SYNC in each
such mode it lists, homing included (lockstep); each that lists none is refused with that
reason on its first line."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.twin import eds_twin
from hil.emulators.errors import EmulatorSetupError
from hil.protocols.cia402 import MODES_BY_CODE
from tests.emulators.drive.test_modes import TR, Drive
from tests.emulators.drive.test_node import enable

DRIVES = Path(__file__).resolve().parents[2] / "data" / "drives"
UNIT = {"0x608F:1": 4096, "0x608F:2": 1}
SERVO = {"0x1000:0": 0x00020192}  # a CiA 402 servo drive: Pilz's and SCHUNK's give no 0x1000
#: file -> (what is supplied, the modes the twin runs)
TWINNED = {
    "ros2_canopen/cia402_slave.eds": ({"0x608F:1": 4096}, "PP PV HM CSP"),
    "maxon/epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf":
        ({**UNIT, "0x6075:0": 2000}, "PP PV HM CSP CSV CST"),
    "nanotec/CL4-E-1-12.eds": ({"0x608F:1": 4096, "0x6075:0": 2000, "0x6073:0": 3000},
                               "PP PV HM CSP CSV CST"),
    "zeroerr/ZeroErr_Driver_V1.5.eds": ({**UNIT, "0x6075:0": 2000}, "PP PV CSP CSV CST"),
    "technosoft/iPOS.D.v1.04.eds": ({"0x608F:1": 4000, "0x6075:0": 2000}, "PP PV HM"),
    "ingenia/eve-net-c_1.8.1.eds": (UNIT, "PP PV HM CSP CSV"),
    "elmo/ElmoSimplIQ.dcf": ({"0x608F:1": 4096, "0x6075:0": 2000, "0x6072:0": 1000,
                              "0x6073:0": 3000}, "PP PV HM"),
    "pilz/prbt_0_1.dcf": ({**UNIT, "0x6075:0": 2000, "0x6073:0": 3000, **SERVO}, "PP"),
    "schunk/Schunk_0_63.dcf": ({**UNIT, "0x6075:0": 2000, "0x6073:0": 3000, **SERVO},
                               "PP"),
}
#: files listing no mode hil emulates
REFUSED = ("elmo/Elmo.dcf", "faulhaber/605.3150.71-A-EK-3-60.eds")


def supplied(values: dict[str, int]) -> tuple[tuple[tuple[int, int], int], ...]:
    return tuple(((int(key[:6], 16), int(key[7:])), value) for key, value in values.items())


def test_every_vendor_file_is_here():
    files = {str(p.relative_to(DRIVES)) for p in DRIVES.rglob("*") if p.suffix in (".eds", ".dcf")}
    assert files == set(TWINNED) | set(REFUSED)


@pytest.mark.parametrize("name", REFUSED)
def test_a_file_listing_no_mode_hil_emulates_is_refused_with_that_first(name):
    with pytest.raises(EmulatorSetupError) as refused:
        eds_twin(str(DRIVES / name), DriveEmulatorConfig())
    assert "no 0x6502 (supported drive modes) with a value" in str(refused.value).splitlines()[0]


def write(drive: Drive, index: int, sub: int, value: int, fmt: str) -> None:
    """A write a master makes, where the file has the object (else the twin's default)."""
    answer = drive.write(index, sub, value, fmt)
    assert answer[0] == 0x60 or struct.unpack_from("<I", answer, 4)[0] == 0x06020000, hex(index)


def drive_in(drive: Drive, mode: str, turn: int) -> None:
    """One move in ``mode`` that ends where CiA 402 says, in the twin's unit (Nanotec's
    0x6072 of 100 per mille leaves the axis a tenth of its current: CSP takes its time)."""
    def counts(deg: float) -> int:
        return round(deg / 360 * turn)
    enable(drive, next(code for code, m in MODES_BY_CODE.items() if m.short == mode))
    for index in (0x6083, 0x6084, 0x609A):
        write(drive, index, 0, counts(720), "<I")
    write(drive, 0x6081, 0, counts(90), "<I")
    if mode == "CST":
        drive.write(0x6071, 0, 100, "<h")
        assert drive.cycles(200)[-1]["velocity"] > 0
    elif mode == "CSP":
        drive.write(0x607A, 0, counts(10), "<i")
        assert abs(drive.cycles(2000)[-1]["position"] - counts(10)) <= counts(0.5)
    elif mode in ("CSV", "PV"):
        drive.write(0x60FF, 0, counts(30), "<i")
        assert abs(drive.cycles(800)[-1]["velocity"] - counts(30)) <= counts(2)
    elif mode == "PP":
        drive.write(0x607A, 0, counts(20), "<i")
        drive.control(0x001F)
        drive.control(0x000F)
        seen = drive.until(TR, 3.0)
        assert abs(seen[-1]["position"] - counts(20)) <= counts(0.5)
    else:  # HM: the position where the axis stands is home
        method = 37 if drive.write(0x6098, 0, 37, "<b")[0] == 0x60 else 35
        drive.write(0x6098, 0, method, "<b")
        home = 100 if drive.write(0x607C, 0, 100, "<i")[0] == 0x60 else 0  # maxon: no 0x607C
        drive.control(0x001F)
        seen = drive.until(0x1400, 2.0, 0x3400)
        assert abs(seen[-1]["position"] - home) <= 1


@pytest.mark.slow  # a second or more: make test runs it, make check does not
@pytest.mark.parametrize("name", sorted(TWINNED))
def test_each_vendor_file_is_twinned_and_driven_in_each_mode_it_lists(name):
    values, modes = TWINNED[name]
    config = DriveEmulatorConfig(eds=str(DRIVES / name), object_values=supplied(values))
    twin = eds_twin(config.eds, config)
    assert twin.summary(1).split("; modes ")[1].split(";")[0] == ", ".join(modes.split())
    for mode in modes.split():
        drive = Drive("cst" if mode != "CST" else "csp", eds=config.eds,
                      object_values=config.object_values)
        try:
            drive_in(drive, mode, twin.counts_per_turn or 0)
        finally:
            drive.close()
