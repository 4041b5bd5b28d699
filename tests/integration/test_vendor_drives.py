"""Every vendor drive file of tests/data/drives (its README: what each lists and lacks) over the
wire, as a user brings one, from a folder outside the repository, lockstep.

Each file that lists a mode hil emulates is twinned with the values its vendor leaves for
commissioning supplied (``hil emulate drive --eds F --set ... --socketcand 127.0.0.1:0``, or
what those flags configure served in this process: :func:`twin_of`);
scanned by ``hil drive scan URL --eds F --json`` (identity, modes and units as the file and what
was supplied give them); and driven in every mode it lists that hil emulates: CST, CSP, CSV and
PV by ``hil servo run`` (0.2 s from where the axis stands: pid in CST, the built-in
``setpoint`` in the others), PP by ``hil drive move`` (done within the drive's position window
0x6067), HM by ``hil drive home`` with each emulated method (done at the method's home point,
which then reads the home offset, statusword bit 12 set), both at a 2 ms SYNC where the file
has 0x1006 (:data:`MOTION_CYCLE`). The ``[master]`` keys stand in for what a file lacks. One
test per file, its steps subtests: one twin per file, however xdist shares the tests out. A
file that lists no mode is refused with that reason on its first line by the twin. The
commands run ``main`` in this process (``hil_here``); :data:`OWN_PROCESS`'s twin runs in a
process of its own, the others' in this process.

:data:`MATRIX` is the table of tests/data/drives/README.md's section "What hil does with each
file" (:func:`matrix_table`), held to it by a test."""

from __future__ import annotations

import contextlib
import functools
import json
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import canopen
import pytest
from canopen.objectdictionary import ODVariable
from canopen.objectdictionary import datatypes as dt

from hil.protocols.cia306 import description_encoding
from tests.cli import hil_here
from tests.drive_processes import start_drive_emulator, stop_drive_emulator
from tests.drive_slave import serve
from tests.served_here import drive_served_here
from tests.vendor_twin import TwinFolder, supplied_cell, twinned_and_refused
from tests.vendor_twin import home as homed
from tests.vendor_twin import move as moved
from tests.vendor_twin import track as tracked

pytestmark = [pytest.mark.slow]

DRIVES = Path(__file__).resolve().parents[1] / "data" / "drives"
SERVO = 0x00020192  # 0x1000 of a CiA 402 servo drive
UNIT = {"0x608F:1": 4096, "0x608F:2": 1}
CYCLIC = ("CST", "CSP", "CSV", "PV")
#: the homing methods the emulated drive runs, in an order each starts within the limit
#: switches (+-190 deg) and not on the index pulse it looks for (one every 360 deg, at 180):
#: 34 and 33 each from a limit switch's edge, 10 deg before theirs (from an index pulse, where
#: the axis stands within the window of it, the next could be a turn on)
HOMING_ORDER = (17, 34, 1, 2, 18, 33, 35, 37)
HOME_OFFSET_DEG = 5.0
NODE = 3  # the LocalNode of a file no twin can be
WINDOW_OFF = 0xFFFF_FFFF  # CiA 402: a position window of all ones is none
OFF_WINDOW_DEG = 1.0      # where the window is off: within a degree all the same
#: the SYNC period of the PP moves and homings of a drive told it (0x1006; hil's default 500
#: us): the drive runs the profile and the search itself, its axis still stepping 500 us, and
#: the master watches its statusword, so 2 ms proves the same in a quarter of the cycles (a
#: drive without 0x1006 keeps its 500 us a SYNC, so runs at hil's default)
MOTION_CYCLE = "cycle_period_us = 2000\n"
#: the file whose twin a user's way starts, ``hil emulate drive --eds F --set ...`` in a process
#: of its own (the most steps, three values supplied); the others' serve in this process (a
#: process start is some 0.45 s of CPU), the same drive on the same wire
OWN_PROCESS = "nanotec/CL4-E-1-12.eds"


@dataclass(frozen=True)
class VendorFile:
    """One vendor file, as the matrix says hil takes it."""

    path: str                  # under tests/data/drives
    vendor: str
    product: str
    listed: tuple[str, ...]    # 0x6502's modes, as the scan names them
    identity: dict[str, int] = field(default_factory=dict)  # 0x1018 as the scan reads it
    supplied: dict[str, int] = field(default_factory=dict)  # --set: what the file leaves out
    stand_ins: dict[str, int] = field(default_factory=dict)  # [master] keys for what it lacks
    counts_per_turn: int = 4096
    driven: tuple[str, ...] = ()  # the modes hil drives it in
    not_twinned: str = ""      # why the twin refuses it
    not_driven: str = ""       # why a mode it lists that hil emulates is not driven
    weak: bool = False         # its own 0x6072 / 0x6073 leave the axis little current

    @property
    def file(self) -> Path:
        return DRIVES / self.path

    def dictionary(self, node_id: int = 1) -> canopen.ObjectDictionary:
        """The file as canopen reads it, for node ``node_id``."""
        with open(self.file, encoding=description_encoding(str(self.file))) as text:
            return canopen.import_od(text, node_id)

    def lists(self, index: int) -> bool:
        """Whether the file has object ``index``."""
        return index in _objects(self.path)


@functools.cache
def _objects(path: str) -> frozenset[int]:
    return frozenset(MATRIX[path].dictionary().keys())


MATRIX = {vendor.path: vendor for vendor in (
    VendorFile("ros2_canopen/cia402_slave.eds", "ROS-Industrial", "CiA 402 test device",
               ("PP", "PV", "HM", "CSP"), {"vendor_id": 0x555, "product_code": 0, "revision": 0},
               {"0x608F:1": 4096}, {"rated_current_mA": 2000}, driven=("PP", "PV", "HM", "CSP")),
    VendorFile("maxon/epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf", "maxon",
               "EPOS4 Module 50/15", ("PP", "PV", "HM", "CSP", "CSV", "CST"),
               {"vendor_id": 0xFB, "product_code": 0x65520000, "revision": 0x01700000,
                "serial": 0x29001321},
               {**UNIT, "0x6075:0": 2000}, {"increments_per_rev": 4096, "rated_current_mA": 2000},
               driven=("PP", "PV", "HM", "CSP", "CSV", "CST")),
    VendorFile("nanotec/CL4-E-1-12.eds", "Nanotec", "CL4-E-1-12",
               ("PP", "VL", "PV", "TQ", "HM", "IP", "CSP", "CSV", "CST"),
               {"vendor_id": 0x26C, "product_code": 0x5A, "revision": 0x85B0000},
               {"0x608F:1": 4096, "0x6075:0": 2000, "0x6073:0": 3000},
               driven=("PP", "PV", "HM", "CSP", "CSV", "CST"), weak=True),
    VendorFile("zeroerr/ZeroErr_Driver_V1.5.eds", "ZeroErr", "eDriver (eRob joints)",
               ("PP", "PV", "TQ", "CSP", "CSV", "CST"),
               {"vendor_id": 0x5A65726F, "product_code": 0x26483052, "revision": 0x20111},
               {**UNIT, "0x6075:0": 2000}, {"increments_per_rev": 4096},
               driven=("PP", "PV", "CSP", "CSV", "CST")),
    VendorFile("technosoft/iPOS.D.v1.04.eds", "Technosoft", "iPOS",
               ("PP", "PV", "HM", "IP", "bit 16", "bit 17", "bit 18", "bit 19", "bit 20"),
               {"vendor_id": 0x1A3}, {"0x608F:1": 4000, "0x6075:0": 2000}, counts_per_turn=4000,
               driven=("PP", "PV", "HM")),
    VendorFile("ingenia/eve-net-c_1.8.1.eds", "Ingenia", "EVE-NET-C",
               ("PP", "PV", "HM", "CSP", "CSV", "bit 16", "bit 17"), {}, UNIT,
               {"increments_per_rev": 4096}, driven=("PP", "PV", "HM", "CSP", "CSV"), weak=True),
    VendorFile("elmo/ElmoSimplIQ.dcf", "Elmo", "SimplIQ (scanned DCF)",
               ("PP", "PV", "TQ", "HM", "IP"), {"vendor_id": 0x9A},
               {"0x608F:1": 4096, "0x6075:0": 2000, "0x6072:0": 1000, "0x6073:0": 3000},
               not_driven="its PDO COB-IDs are read-only (static PDOs, as scanned from the "
               "drive): hil maps its own, and the scan and a run refuse it naming 0x1400:1"),
    VendorFile("pilz/prbt_0_1.dcf", "Pilz", "PRBT joint module", ("PP", "VL", "IP"), {},
               {**UNIT, "0x6075:0": 2000, "0x6073:0": 3000, "0x1000:0": SERVO},
               {"increments_per_rev": 4096}, driven=("PP",)),
    VendorFile("schunk/Schunk_0_63.dcf", "SCHUNK", "PRL120 rotary actuator", ("PP", "VL", "IP"),
               {}, {**UNIT, "0x6075:0": 2000, "0x6073:0": 3000, "0x1000:0": SERVO},
               {"increments_per_rev": 4096}, driven=("PP",)),
    VendorFile("elmo/Elmo.dcf", "Elmo", "Gold drive", (),
               not_twinned="0x6502 (supported drive modes) has no value"),
    VendorFile("faulhaber/605.3150.71-A-EK-3-60.eds", "FAULHABER", "MCBL motion controller", (),
               not_twinned="it has no 0x6502 (supported drive modes)"),
)}
TWINNED, REFUSED = twinned_and_refused(MATRIX)


def matrix_table() -> str:
    """The matrix as tests/data/drives/README.md shows it."""
    rows = ["| vendor | product | file | modes listed | twinned | driven in | supplied |",
            "| --- | --- | --- | --- | --- | --- | --- |"]
    for vendor in MATRIX.values():
        driven = ", ".join(vendor.driven) or f"none: {vendor.not_driven}" \
            if not vendor.not_twinned else "-"
        named = [mode for mode in vendor.listed if not mode.startswith("bit ")]
        listed = " ".join(named) + (" + vendor bits" if len(named) < len(vendor.listed) else "")
        rows.append(f"| {vendor.vendor} | {vendor.product} | `{vendor.path}` | "
                    f"{listed or '-'} | "
                    f"{'no: ' + vendor.not_twinned if vendor.not_twinned else 'yes'} | "
                    f"{driven} | {supplied_cell(vendor.supplied, vendor.stand_ins)} |")
    return "\n".join(rows)


def test_the_matrix_holds_every_vendor_file_and_the_readme_shows_it():
    files = {str(p.relative_to(DRIVES)) for p in DRIVES.rglob("*") if p.suffix in (".eds", ".dcf")}
    assert files == set(MATRIX)
    readme = (DRIVES / "README.md").read_text()
    section = readme.split("## What hil does with each file\n", 1)[1]
    assert matrix_table() in section


# -- the twins -------------------------------------------------------------------------------
@dataclass
class Twin(TwinFolder):
    """A vendor file's twin over socketcand, and the folder (outside the repository) its
    commands run from."""

    vendor: VendorFile

    def motion_cycle(self) -> str:
        """The ``[master]`` key of its moves and homings: :data:`MOTION_CYCLE` where it has
        0x1006."""
        return MOTION_CYCLE if self.vendor.lists(0x1006) else ""

    def position_window_deg(self) -> float:
        """The drive's position window 0x6067 [deg] as ``hil drive sdo read`` reads it (a
        file without one: the twin's, hil's tenth of a degree to the increment), and the wire's
        resolution: one increment."""
        counts = self.vendor.counts_per_turn
        if not self.vendor.lists(0x6067):
            return (max(1, round(counts / 3600)) + 1) * 360 / counts
        read = self.hil("drive", "sdo", "read", self.url, "0x6067", "--type", "u32", "--json")
        assert read.returncode == 0, read.stderr
        window = json.loads(read.stdout)["value"]
        return OFF_WINDOW_DEG if window == WINDOW_OFF else (window + 1) * 360 / counts


@contextlib.contextmanager
def twin_of(vendor: VendorFile, folder: Path, capsys: pytest.CaptureFixture[str]
            ) -> Iterator[Twin]:
    """The twin of ``vendor`` on socketcand 127.0.0.1, its commands run from ``folder``."""
    with twin_url(vendor, folder) as url:
        yield Twin(url, folder, capsys, vendor.stand_ins, vendor)


@contextlib.contextmanager
def twin_url(vendor: VendorFile, folder: Path) -> Iterator[str]:
    """Where the twin of ``vendor`` serves: for :data:`OWN_PROCESS`, ``hil emulate drive --eds
    F --set ... --socketcand 127.0.0.1:0`` from ``folder``; for the others, the same served in
    this process (:func:`tests.served_here.drive_served_here`), of a config whose ``[emulator]
    eds`` and ``set`` are what those flags lay over the defaults."""
    if vendor.path == OWN_PROCESS:
        sets = [arg for key, value in vendor.supplied.items()
                for arg in ("--set", f"{key}={value}")]
        proc, port = start_drive_emulator(None, 0, "--eds", str(vendor.file), *sets,
                                          cwd=folder)
        try:
            yield f"socketcand://127.0.0.1:{port}"
        finally:
            stop_drive_emulator(proc)
    else:
        values = ", ".join(f"{json.dumps(key)} = {value}"
                           for key, value in vendor.supplied.items())
        config = folder / "twin.toml"
        config.write_text(f"[emulator]\neds = {json.dumps(str(vendor.file))}\n"
                          f"set = {{{values}}}\n")
        with drive_served_here(config) as here:
            yield here.url


@pytest.mark.parametrize("path", TWINNED)
def test_each_vendor_file_is_twinned_scanned_and_driven_in_each_mode_it_lists(
        path, tmp_path, capsys, subtests):
    """One twin per file, every step of it a subtest: the scan, then each mode it is driven
    in (the cyclic ones first, from where the axis stands; PP; then the homings)."""
    vendor = MATRIX[path]
    with twin_of(vendor, tmp_path, capsys) as twin:
        with subtests.test("scan"):
            scanned(twin)
        if not vendor.driven:
            with subtests.test("refused"):
                refused(twin)
        for mode in vendor.driven:
            with subtests.test(mode):
                if mode in CYCLIC:
                    track(twin, mode)
                elif mode == "PP":
                    move(twin)
                else:
                    home(twin, subtests)


def scanned(twin: Twin) -> None:
    """``hil drive scan --eds``: identity, modes and units as the file and what was supplied
    give them; drivable in the mode it is driven in last."""
    vendor = twin.vendor
    mode = (vendor.driven or ("PP",))[-1].lower()
    scan = twin.hil("drive", "scan", twin.url, "--eds", vendor.file, "--config",
                    twin.config(mode), "--json")
    [node] = json.loads(scan.stdout)["nodes"]
    assert node["identity"] == vendor.identity
    assert node["modes"] == list(vendor.listed)
    assert node["scaling"]["counts_per_turn"] == vendor.counts_per_turn
    assert node["scaling_from"]["increments_per_rev"] == (
        "[master] increments_per_rev" if "increments_per_rev" in vendor.stand_ins else "0x608F:1")
    if vendor.driven:
        assert scan.returncode == 0 and node["verdict"].startswith(
            f"can drive: yes, in {mode.upper()}"), node["verdict"]
    else:  # one reason a line, the read-only COB-IDs first
        assert scan.returncode == 1 and node["problems"][0] == (
            f"EDS {vendor.file}: 0x1400:1 is read-only: hil needs it writable, 32 bits, to set "
            "up the cyclic PDOs")


def refused(twin: Twin) -> None:
    """A run with the file as its --eds is refused before anything is written."""
    vendor = twin.vendor
    moved = twin.hil("drive", "move", twin.url, "10", "--eds", vendor.file, "--config",
                     twin.config("pp"), "--out", "never.mcap")
    assert moved.returncode == 2 and moved.stderr.startswith(
        f"hil: error: drive node 1 (EDS {vendor.file}): 0x1400:1 is read-only"), moved.stderr
    assert not (twin.folder / "never.mcap").exists()


def track(twin: Twin, mode: str) -> None:
    """``hil servo run`` (:func:`tests.vendor_twin.track`); PV with a profile acceleration
    that lets the drive's ramp follow the sine. Lockstep: the twin keeps the master's SYNC
    time."""
    profile = ""
    if mode == "PV":
        profile = "[profile]\nacceleration_deg_s2 = 36000.0\n" + (
            "deceleration_deg_s2 = 36000.0\n" if twin.vendor.lists(0x6084) else "")
    tracked(twin, mode, profile)


def move(twin: Twin) -> None:
    """``hil drive move`` 30 deg on: done (statusword bit 10) within the drive's position
    window, at a speed its current allows."""
    moved(twin, twin.position_window_deg(), twin.vendor.lists(0x6084), twin.motion_cycle())


def home(twin: Twin, subtests: pytest.Subtests) -> None:
    """``hil drive home`` with each emulated method: done at the method's home point, which
    then reads the home offset 0x607C, within the drive's position window; statusword bits 12
    (homing attained) and 10."""
    vendor = twin.vendor
    speeds = ("--speed", 180, "--zero-speed", 90) if vendor.weak else \
        ("--speed", 360, "--zero-speed", 180)
    accelerate = ("--homing-acceleration", 720 if vendor.weak else 3600) \
        if vendor.lists(0x609A) else ()
    offset = HOME_OFFSET_DEG if vendor.lists(0x607C) else 0.0  # maxon's has none: 0
    given = ("--offset", offset) if offset else ()
    window_deg = twin.position_window_deg()
    for method in HOMING_ORDER:
        with subtests.test(f"HM {method}"):
            homed(twin, method, (*given, *speeds, *accelerate), offset, window_deg,
                  twin.motion_cycle())


# -- the files no twin can be -------------------------------------------------------------------
@pytest.fixture
def described_by(monkeypatch):
    """canopen's LocalNode with the dictionary a vendor file describes (tests/drive_slave.py),
    node 3 on a virtual bus of its own."""
    monkeypatch.setattr(canopen.Network, "NOTIFIER_CYCLE", 0.1)
    networks = []

    def start(vendor: VendorFile) -> str:
        od = vendor.dictionary(NODE)
        if 0x1017 not in od:  # canopen's LocalNode needs it for its own heartbeat
            heartbeat = ODVariable("Producer heartbeat time", 0x1017, 0)
            heartbeat.data_type, heartbeat.access_type, heartbeat.default = dt.UNSIGNED16, "rw", 0
            od.add_object(heartbeat)
        url = f"virtual://vendor-{uuid.uuid4().hex}"
        networks.append(serve(url, NODE, od=od)[0])
        return url

    yield start
    for network in networks:
        network.disconnect()


@pytest.mark.parametrize("path", REFUSED)
def test_a_file_listing_no_mode_is_refused_by_the_twin_with_that_first(tmp_path, capsys, path,
                                                                      described_by):
    """The twin cannot tell which modes to emulate. hil's master can drive a drive without
    0x6502 (it checks the mode by 0x6061), so the scan of a drive the file describes does not
    refuse it for that: it lists no modes, and says what else stands in the way (Elmo's Gold
    DCF gives 0x6075 = 0; FAULHABER's EDS, read although not UTF-8, has static PDOs)."""
    vendor = MATRIX[path]
    refused = hil_here(capsys, "emulate", "drive", "--eds", vendor.file, "--socketcand",
                       "127.0.0.1:0", cwd=tmp_path)
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    assert refused.stderr.splitlines()[0] == (
        f"hil: error: EDS {vendor.file}: no 0x6502 (supported drive modes) with a value: the "
        "twin emulates the modes it lists (PP, PV, HM, CSP, CSV, CST)")
    (tmp_path / "pp.toml").write_text('[master]\nmode = "pp"\n')
    scan = hil_here(capsys, "drive", "scan", described_by(vendor), "--node", NODE, "--eds",
                    vendor.file, "--config", "pp.toml", "--json", cwd=tmp_path)
    assert scan.returncode == 1, scan.stderr
    [node] = json.loads(scan.stdout)["nodes"]
    assert node["supported_modes"] is None and node["modes"] == []
    assert REFUSED_SCAN[path].format(file=vendor.file) in node["problems"]


#: what the scan of a drive each refused file describes says, among its reasons
REFUSED_SCAN = {
    "elmo/Elmo.dcf": "its position and current cannot be scaled: rated current 0x6075 is 0 mA: "
                     "the torque objects would mean nothing",
    "faulhaber/605.3150.71-A-EK-3-60.eds": "EDS {file}: 0x1400:1 is read-only: hil needs it "
                                           "writable, 32 bits, to set up the cyclic PDOs",
}
