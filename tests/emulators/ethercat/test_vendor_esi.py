"""Vendor ESI files (tests/data/esi/<vendor>/, their table in its README.md) as the slave's SII
and, where the file has a <Dictionary>, its twin's objects, by the twin's rules: values the
vendor leaves empty come from ``--set``, modes from 0x6502, a file the twin cannot run is
refused with the deciding reason on its first line. SOEM (a master hil did not write) scans
the slave built from the Ingenia file."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.twin import eds_twin
from hil.emulators.errors import EmulatorSetupError
from hil.emulators.ethercat.esi import sii_from_esi
from tests.emulators.drive.test_vendor_files import provenance
from tests.ethercat_netns import REPO, soem_on, veth_pair

ESI = Path(__file__).resolve().parents[2] / "data" / "esi"
INGENIA = ESI / "ingenia" / "EVS-NET-01_ingenia_esi.xml"
STMBL = ESI / "stmbl" / "STMBL_ECAT.xml"
# what the Ingenia file leaves for commissioning: the encoder's increments per revolution
INGENIA_SET = ("--set", "0x608F:1=4096", "--set", "0x608F:2=1")


def test_each_file_is_where_its_source_md_says_with_its_sha256_and_in_the_table():
    readme = (ESI / "README.md").read_text(encoding="utf-8")
    for path in (INGENIA, STMBL):
        row = provenance(path.parent / "SOURCE.md")[path.name]
        assert row["sha256"].strip("`") == hashlib.sha256(path.read_bytes()).hexdigest()
        assert f"`{path.parent.name}/{path.name}`" in readme


@pytest.mark.parametrize(("path", "identity", "name"), [
    (INGENIA, (0x29C, 61935618, 327685), "EVS-NET-01"),
    (STMBL, (4919, 0x20192, 1), "STMBL ECAT"),
])
def test_the_sii_takes_each_files_identity(path, identity, name):
    sii = sii_from_esi(str(path))
    assert (sii.vendor_id, sii.product_code, sii.revision) == identity
    assert sii.name == name


def test_the_ingenia_file_is_a_twin_with_the_modes_its_0x6502_lists():
    config = replace(DriveEmulatorConfig(), object_values=(((0x608F, 1), 4096),
                                                           ((0x608F, 2), 1)))
    twin = eds_twin(str(INGENIA), config)
    # 0x6502 = 0x000F03E5: PP PV HM IP CSP CSV CST and vendor bits; IP not emulated. HM: its
    # 0x6099 is an array (ArrayInfo) whose elements are sub-indices 1 and 2
    assert twin.summary(1).count("modes PP, PV, HM, CSP, CSV, CST") == 1
    assert [twin.od[0x6099][sub].name for sub in (1, 2)] == [
        "Homing search velocities 1", "Homing search velocities 2"]
    assert 0x6502 in twin.od


def test_the_ingenia_file_without_its_encoder_unit_is_refused_naming_it():
    with pytest.raises(EmulatorSetupError) as refused:
        eds_twin(str(INGENIA), DriveEmulatorConfig())
    first = str(refused.value).splitlines()[0]
    assert first.startswith(f"ESI {INGENIA}: no 0x608F:1 (encoder increments)")
    assert "--set 0x608F:1=VALUE" in first


def test_the_stmbl_file_is_refused_for_its_empty_0x6502():
    with pytest.raises(EmulatorSetupError) as refused:
        eds_twin(str(STMBL), DriveEmulatorConfig())
    assert str(refused.value).splitlines()[0] == (
        f"ESI {STMBL}: no 0x6502 (supported drive modes) with a value: the twin emulates the "
        "modes it lists (PP, PV, HM, CSP, CSV, CST)")


def hil(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=120, env=env)


@pytest.mark.slow  # a process of its own: make test runs it, make check does not
def test_the_refusal_from_the_command_line_is_one_line(tmp_path):
    out = hil(tmp_path, "emulate", "drive", "--ethercat", "hil-no-such-if", "--esi",
              str(STMBL))
    assert out.returncode != 0
    lines = out.stderr.strip().splitlines()
    assert "no 0x6502 (supported drive modes) with a value" in lines[0]
    assert "Traceback" not in out.stderr


@pytest.mark.slow
def test_soem_scans_the_ingenia_slave_and_reads_its_identity_and_modes(tmp_path):
    pytest.importorskip("pysoem", reason="the ethercat extra is not installed")

    with veth_pair() as veth, soem_on(veth, "--esi", str(INGENIA), *INGENIA_SET) as master:
        assert master.config_init() == 1
        slave = master.slaves[0]
        assert (slave.man, slave.id, slave.rev, slave.name) == (
            0x29C, 61935618, 327685, "EVS-NET-01")
        modes = int.from_bytes(slave.sdo_read(0x6502, 0), "little")
        assert modes == 0x000F03E5  # the file's DefaultData, through CoE
