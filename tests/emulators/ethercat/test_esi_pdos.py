"""The PDOs of an ESI file's twin on EtherCAT (Ingenia's EVS-NET-01 file, and copies of it
changed by one attribute): the mapping objects are the dictionary's or the ``<RxPdo>`` /
``<TxPdo>`` elements', a Fixed map is read-only, 0x1C12 / 0x1C13 hold what the dictionary
says, an Exclude'd pair is refused, a Mandatory PDO left out keeps the slave out of SAFE-OP,
and a Fixed PDO hil's master maps is a refusal line of the twin."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.twin import eds_twin
from hil.emulators.errors import EmulatorSetupError
from hil.emulators.ethercat.esi import sii_from_esi
from hil.emulators.ethercat.slave import EthercatDrive
from hil.protocols.cia301 import (
    ABORT_NO_SUBINDEX,
    ABORT_READ_ONLY,
    ABORT_VALUE,
    SdoAbortError,
)
from hil.protocols.ethercat import (
    AL_INVALID_INPUT_CONFIG,
    RXPDO_ASSIGN,
    SAFE_OP,
    TXPDO_ASSIGN,
)

INGENIA = Path(__file__).resolve().parents[2] / "data" / "esi" / "ingenia" / \
    "EVS-NET-01_ingenia_esi.xml"
UNIT = (((0x608F, 1), 4096), ((0x608F, 2), 1))
RPDO1 = '<RxPdo Fixed="0" Sm="2">'
TPDO1 = '<TxPdo Fixed="0" Sm="3">'
#: a PDO only an element describes (the file's dictionary has no 0x1603)
RPDO4 = """<RxPdo Fixed="0"><Index>#x1603</Index><Name>Torque</Name>
          <Entry><Index>#x6040</Index><SubIndex>0</SubIndex><BitLen>16</BitLen></Entry>
          <Entry><Index>#x6071</Index><SubIndex>0</SubIndex><BitLen>16</BitLen></Entry>
        </RxPdo>
        """


def twin_of(path: Path | str) -> EthercatDrive:
    config = replace(DriveEmulatorConfig(), eds=str(path), object_values=UNIT)
    return EthercatDrive(config, sii=sii_from_esi(str(path)), pdos_from_sii=True)


def changed(tmp_path: Path, old: str, new: str) -> Path:
    """A copy of the Ingenia file with ``old`` (found once) replaced by ``new``."""
    text = INGENIA.read_text(encoding="utf-8")
    assert text.count(old) == 1
    path = tmp_path / "changed.xml"
    path.write_text(text.replace(old, new, 1), encoding="utf-8")
    return path


def abort(call) -> int:
    with pytest.raises(SdoAbortError) as refused:
        call()
    return refused.value.code


@pytest.fixture(scope="module")
def ingenia() -> EthercatDrive:
    return twin_of(INGENIA)


def test_the_twin_serves_the_files_pdos_and_its_power_on_assignment(ingenia):
    pdos = ingenia.node.pdos.by_object
    assert sorted(pdos) == [0x1600, 0x1601, 0x1602, 0x1A00, 0x1A01, 0x1A02]
    # no CAN frame carries them: 0x1600's power-on map of 88 bits is served as the file has it
    assert pdos[0x1600].keys == ((0x6040, 0), (0x607A, 0), (0x60FF, 0), (0x6060, 0))
    # 0x1601's first entry, empty in the dictionary, is its element's
    assert pdos[0x1601].keys == ((0x6040, 0), (0x607A, 0))
    # the dictionary's 0x1C12: three sub-indices, none assigned at power-on
    assert ingenia.assignment[RXPDO_ASSIGN].read(0) == b"\x00"
    assert abort(lambda: ingenia.assignment[RXPDO_ASSIGN].read(4)) == ABORT_NO_SUBINDEX
    assert ingenia.output_size == ingenia.input_size == 0


def test_two_pdos_one_excludes_are_refused_together():
    inputs = twin_of(INGENIA).assignment[TXPDO_ASSIGN]
    inputs.write(1, 0x1A00)
    inputs.write(2, 0x1A01)  # 0x1A00 <Exclude>s 0x1A01
    assert abort(lambda: inputs.write(0, 2)) == ABORT_VALUE
    inputs.write(0, 1)
    assert inputs.assigned == [0x1A00]


def test_a_pdo_only_an_element_describes_is_made_from_it(tmp_path):
    drive = twin_of(changed(tmp_path, TPDO1, RPDO4 + TPDO1))
    assert drive.node.pdos.by_object[0x1603].keys == ((0x6040, 0), (0x6071, 0))
    outputs = drive.assignment[RXPDO_ASSIGN]
    outputs.write(1, 0x1603)
    outputs.write(0, 1)
    assert drive.output_size == 4


def test_a_fixed_map_is_read_only(tmp_path):
    drive = twin_of(changed(tmp_path, '<RxPdo Fixed="0">\n          <Index DependOnSlot="true">'
                            '#x1601', '<RxPdo Fixed="1">\n          <Index DependOnSlot="true">'
                            '#x1601'))
    assert abort(lambda: drive.node.download(0x1601, 0, b"\x00")) == ABORT_READ_ONLY


def test_a_mandatory_pdo_left_out_keeps_the_slave_out_of_safe_op(tmp_path):
    drive = twin_of(changed(tmp_path, TPDO1, '<TxPdo Fixed="0" Sm="3" Mandatory="true">'))
    assert drive.refuse(SAFE_OP) == AL_INVALID_INPUT_CONFIG
    inputs = drive.assignment[TXPDO_ASSIGN]
    inputs.write(1, 0x1A00)
    inputs.write(0, 1)
    assert drive.refuse(SAFE_OP) == 0


def test_a_fixed_pdo_hils_master_maps_is_a_refusal_line_of_the_twin(tmp_path):
    path = changed(tmp_path, RPDO1, '<RxPdo Fixed="1" Sm="2">')
    with pytest.raises(EmulatorSetupError) as refused:
        eds_twin(str(path), replace(DriveEmulatorConfig(), object_values=UNIT))
    assert str(refused.value).splitlines() == [
        f"ESI {path}: RxPDO 0x1600 (RPDO 1 mapping parameter) is Fixed: hil's master maps its "
        "own objects into it (hil remaps PDOs; it does not adopt a fixed map)"]
