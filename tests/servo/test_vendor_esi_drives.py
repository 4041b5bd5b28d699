"""Every vendor ESI file of tests/data/esi (its README: what each lists and lacks) as a user
brings one to hil's EtherCAT master, from a folder outside the repository, lockstep, over a
veth pair in a namespace of the test's own.

Each file that lists a mode hil emulates is twinned by ``hil emulate drive --ethercat IFACE
--esi F --set ...`` (a process of its own: its SII, objects and PDOs from the file, the values
its vendor leaves for commissioning supplied); scanned by ``hil drive scan ethercat://IFACE
--json`` (the SII's identity, the modes 0x6502 lists); and driven in every mode it lists that
hil emulates: CST, CSP, CSV and PV by ``hil servo run`` (0.2 s from where the axis stands: pid
in CST, the built-in ``setpoint`` in the others), PP by ``hil drive move``, HM by ``hil drive
home`` (a method that searches a switch, one that homes where the axis stands). The
``[master]`` keys stand in for what a file lacks (Ingenia's 0x1A00 excludes 0x1A01, so its
feedback comes in one TxPDO: ``tpdo_layout = "one"``). A file the twin cannot run is refused
with the deciding reason on its first line and every Fixed PDO hil's master maps named on one
of its own. The commands run ``main`` in this process, in the namespace (``hil_here``); each
twin in its own process.

:data:`MATRIX` is the table of tests/data/esi/README.md's section "Driven by hil's master"
(:func:`matrix_table`), held to it by a test."""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from hil.emulators.ethercat.esi_dictionary import od_from_esi
from tests.cli import hil_here
from tests.ethercat_netns import inside, slave_on, veth_pair
from tests.vendor_twin import TwinFolder, supplied_cell, twinned_and_refused
from tests.vendor_twin import home as homed
from tests.vendor_twin import move as moved
from tests.vendor_twin import track as tracked

pytest.importorskip("pysoem", reason="the ethercat extra (pysoem) is not installed")

pytestmark = pytest.mark.slow

ESI = Path(__file__).resolve().parents[1] / "data" / "esi"
SERVO = 0x00020192  # 0x1000 of a CiA 402 servo drive
CYCLIC = ("CST", "CSP", "CSV", "PV")

@dataclass(frozen=True)
class EsiFile:
    """One vendor ESI file, as the matrix says hil takes it."""

    path: str                  # under tests/data/esi
    vendor: str
    product: str
    identity: tuple[int, int, int]  # 0x1018 over CoE: vendor id, product code, revision
    listed: tuple[str, ...] = ()     # 0x6502's modes, as the scan names them
    supplied: dict[str, int] = field(default_factory=dict)  # --set: what the file leaves out
    stand_ins: dict[str, object] = field(default_factory=dict)  # [master] keys
    driven: tuple[str, ...] = ()     # the modes hil drives it in
    not_driven: str = ""             # why a mode it lists that the twin emulates is not
    not_twinned: tuple[str, ...] = ()  # the twin's refusal: its lines, deciding one first

    @property
    def file(self) -> Path:
        return ESI / self.path

    def lists(self, index: int) -> bool:
        """Whether the file's dictionary has object ``index``."""
        return index in _objects(self.path)


@functools.cache
def _objects(path: str) -> frozenset[int]:
    return frozenset(od_from_esi(str(ESI / path), 1).keys())


INGENIA_MODES = ("PP", "PV", "HM", "IP", "CSP", "CSV", "CST", "bit 16", "bit 17", "bit 18",
                 "bit 19")
FIXED = "is Fixed: hil's master maps its own objects into it (hil remaps PDOs; it does not " \
    "adopt a fixed map)"
MATRIX = {esi.path: esi for esi in (
    EsiFile("ingenia/EVS-NET-01_ingenia_esi.xml", "Ingenia", "EVS-NET-01",
            (0x29C, 0x32, 0), INGENIA_MODES,  # its SII's: 0x29C, 61935618, 327685
            {"0x608F:1": 4096, "0x608F:2": 1, "0x1000:0": SERVO},
            {"increments_per_rev": 4096, "tpdo_layout": "one"},
            driven=("CST", "CSP", "CSV", "PV", "PP", "HM")),
    EsiFile("stmbl/STMBL_ECAT.xml", "STMBL (kubabuda)", "STMBL ECAT", (4919, 0x20192, 1),
            not_twinned=(
                "no 0x6502 (supported drive modes) with a value: the twin emulates the modes "
                "it lists (PP, PV, HM, CSP, CSV, CST)",
                "0x6064:0 (Position actual) is UNSIGNED32, the twin's is INTEGER32",
                "0x607A:0 (Target position) is UNSIGNED32, the twin's is INTEGER32",
                f"RxPDO 0x1600 (Control Word) {FIXED}",
                f"TxPDO 0x1A00 (Status Word) {FIXED}",
                f"TxPDO 0x1A01 (Position actual) {FIXED}")),
)}
TWINNED, REFUSED = twinned_and_refused(MATRIX)


def matrix_table() -> str:
    """The matrix as tests/data/esi/README.md shows it."""
    rows = ["| file | twinned | driven in (lockstep, over a veth pair) | supplied |",
            "| --- | --- | --- | --- |"]
    for esi in MATRIX.values():
        refusal = "; ".join(esi.not_twinned)
        driven = "; not ".join(filter(None, (", ".join(esi.driven), esi.not_driven)))
        rows.append(f"| `{esi.path}` | {'no: ' + refusal if refusal else 'yes'} | "
                    f"{driven or '-'} | {supplied_cell(esi.supplied, esi.stand_ins)} |")
    return "\n".join(rows)


def test_the_matrix_holds_every_esi_file_and_the_readme_shows_it():
    files = {str(p.relative_to(ESI)) for p in ESI.rglob("*.xml")}
    assert files == set(MATRIX)
    section = (ESI / "README.md").read_text().split("## Driven by hil's master\n", 1)[1]
    assert matrix_table() in section


@dataclass
class Twin(TwinFolder):
    """A vendor ESI's twin on the slave end of ``veth``, and the folder (outside the
    repository) hil's commands run from, in the namespace."""

    esi: EsiFile


@pytest.mark.parametrize("path", TWINNED)
def test_each_vendor_esi_is_twinned_scanned_and_driven_in_each_mode_it_lists(
        path, tmp_path, capsys, subtests):
    """One twin per file, every step of it a subtest: the scan, then each mode it is driven
    in (the cyclic ones from where the axis stands, then PP, then HM)."""
    esi = MATRIX[path]
    sets = [arg for key, value in esi.supplied.items() for arg in ("--set", f"{key}={value}")]
    with veth_pair() as veth, slave_on(veth, "--esi", str(esi.file), *sets), inside(veth):
        twin = Twin(f"ethercat://{veth.master}?slave=1", tmp_path, capsys, esi.stand_ins, esi)
        with subtests.test("scan"):
            scanned(twin, f"ethercat://{veth.master}")
        for mode in esi.driven:
            with subtests.test(mode):
                if mode in CYCLIC:
                    track(twin, mode)
                elif mode == "PP":
                    move(twin)
                else:
                    home(twin)


def scanned(twin: Twin, segment: str) -> None:
    """``hil drive scan``: the identity 0x1018 gives, the SII's name, the modes 0x6502 lists,
    drivable in the mode it is driven in first."""
    esi = twin.esi
    mode = esi.driven[0].lower()
    scan = twin.hil("drive", "scan", segment, "--config", twin.config(mode), "--json")
    [node] = json.loads(scan.stdout)["nodes"]
    assert (node["identity"]["vendor_id"], node["identity"]["product_code"],
            node["identity"]["revision"]) == esi.identity
    assert node["device_name"] == esi.product and node["nmt_state"] == "AL PRE-OP"
    assert node["modes"] == list(esi.listed)
    assert scan.returncode == 0 and node["verdict"].startswith(
        f"can drive: yes, in {mode.upper()}"), node["verdict"]


def track(twin: Twin, mode: str) -> None:
    """``hil servo run`` (:func:`tests.vendor_twin.track`), the twin on the master's
    process-data cycles: completed, a current that moved the axis (in CST hil's, clamped), in
    OP with the working counter of one slave."""
    kpis, events = tracked(twin, mode)
    assert kpis["status"] == "completed" and kpis["peak_current_mA"] > 0
    if mode == "CST":  # hil's current, clamped (in the others the drive chooses it)
        assert kpis["peak_current_mA"] <= kpis["current_limit_mA"]
    assert "in OP, working counter 3 a cycle" in events["ethercat.operational"]


def move(twin: Twin) -> None:
    """``hil drive move`` 30 deg on: done (statusword bit 10) within a degree."""
    moved(twin, 1.0, twin.esi.lists(0x6084))


def home(twin: Twin) -> None:
    """``hil drive home`` by a method that searches the home switch (17) and one that homes
    where the axis stands (37): done at home (the position 0, no home offset given) with
    statusword bits 12 and 10; with one TxPDO the new zero is not taken for a speed."""
    for method in (17, 37):
        homed(twin, method, ("--speed", 360, "--zero-speed", 180), 0.0, 1.0)


@pytest.mark.parametrize("path", REFUSED)
def test_a_file_the_twin_cannot_run_is_refused_one_reason_a_line(tmp_path, capsys, path):
    """From outside the repository, before any interface is opened: the deciding reason
    first, then every other, each a line (the Fixed PDOs hil's master maps among them)."""
    esi = MATRIX[path]
    out = hil_here(capsys, "emulate", "drive", "--ethercat", "hil-no-such-if", "--esi",
                   esi.file, cwd=tmp_path)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    lines = out.stderr.strip().splitlines()
    assert lines == [f"hil: error: ESI {esi.file}: {esi.not_twinned[0]}"] + [
        f"ESI {esi.file}: {line}" for line in esi.not_twinned[1:]]
