"""The twin takes the files vendors publish, each quirk proven with the EX-20's EDS edited to
have it: values left empty for commissioning (supplied by ``--set``, ``[emulator] set`` or a
DCF's ParameterValue, else one line naming the object and how), a unit the file lacks, a
signed type where CiA 402's values are never negative, power-on PDO maps it cannot serve (the
master maps its own; a map it cannot serve is refused when written), PDOs invalid at power-on,
and a refusal whose deciding reason comes first, one problem a line."""

from __future__ import annotations

import struct
from pathlib import Path

from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.twin import eds_twin
from tests.cli import hil_here
from tests.emulators.drive.test_eds_twin import COUNTS_PER_TURN, EX20, edited, one_error_line
from tests.emulators.drive.test_node import Wire, abort_code

EMPTY_RATED = ("[6075]\nParameterName=Motor rated current\nObjectType=0x7\nDataType=0x0007\n"
               "AccessType=rw\nDefaultValue=2000\n")


def without_rated_current(tmp_path: Path, name: str = "empty.eds") -> Path:
    return edited(tmp_path, EMPTY_RATED, EMPTY_RATED.replace("DefaultValue=2000\n",
                                                              "DefaultValue=\n"), name)


def test_an_empty_commissioning_value_is_one_line_naming_how_to_give_it(tmp_path, capsys):
    refused = hil_here(capsys, "emulate", "drive", "--eds", without_rated_current(tmp_path),
                       cwd=tmp_path)
    assert one_error_line(refused).endswith(
        "0x6075:0 (Motor rated current) has no value: the twin takes the axis' units and "
        "current limits from the file, never its own; give it with --set 0x6075:0=VALUE or "
        "[emulator] set = {\"0x6075:0\" = VALUE} (or a DCF's ParameterValue)")


def test_an_empty_value_comes_from_set_flag_config_or_dcf(tmp_path, capsys):
    path = without_rated_current(tmp_path)
    flag = hil_here(capsys, "emulate", "drive", "--eds", path, "--set", "0x6075:0=1500",
                    cwd=tmp_path)
    assert flag.returncode == 0, flag.stderr
    (tmp_path / "set.toml").write_text('[emulator]\neds = "empty.eds"\n'
                                       'set = {"0x6075:0" = 1500}\n')
    config = hil_here(capsys, "emulate", "drive", "--config", "set.toml", cwd=tmp_path)
    assert config.returncode == 0, config.stderr
    dcf = edited(tmp_path, EMPTY_RATED, EMPTY_RATED.replace(
        "DefaultValue=2000\n", "DefaultValue=\nParameterValue=1500\n"), "drive.dcf")
    for twin_of in (path, dcf):
        given = (("0x6075:0", 1500),) if twin_of == path else ()
        wire = Wire(eds=str(twin_of), object_values=tuple(
            ((int(k[:6], 16), 0), v) for k, v in given))
        try:
            assert struct.unpack_from("<I", wire.read(0x6075), 4)[0] == 1500
        finally:
            wire.close()
    flag_over_config = hil_here(capsys, "emulate", "drive", "--config", "set.toml", "--set",
                                "0x6075:0=x", cwd=tmp_path)
    assert flag_over_config.returncode == 2
    assert "--set: give INDEX:SUB=VALUE, e.g. 0x6075:0=2000, got '0x6075:0=x'" in \
        flag_over_config.stderr


def test_a_device_type_left_empty_is_refused_until_set(tmp_path, capsys):
    """Pilz's and SCHUNK's DCFs give 0x1000 no value: a twin serving it empty answered a
    master's first read with abort 0x08000024, and no master could take the drive."""
    path = edited(tmp_path, "DefaultValue=0x00020192\n", "DefaultValue=\n")
    refused = hil_here(capsys, "emulate", "drive", "--eds", path, cwd=tmp_path)
    assert one_error_line(refused).endswith(
        "0x1000:0 (device type) has no value; give it with --set 0x1000:0=VALUE or [emulator] "
        "set = {\"0x1000:0\" = VALUE} (or a DCF's ParameterValue): every CANopen device has "
        "it (CiA 301), and a master reads it first")
    wire = Wire(eds=str(path), object_values=(((0x1000, 0), 0x00020192),))
    try:
        assert struct.unpack_from("<I", wire.read(0x1000), 4)[0] == 0x00020192
    finally:
        wire.close()


def test_a_unit_the_file_lacks_comes_from_set_and_stays_hidden(tmp_path, capsys):
    text = EX20.read_text()
    start, end = text.index("[608F]\n"), text.index("[6091]\n")
    path = tmp_path / "no608f.eds"
    path.write_text(text[:start] + text[end:])
    refused = hil_here(capsys, "emulate", "drive", "--eds", path, cwd=tmp_path)
    assert "no 0x608F:1 (encoder increments): the twin needs the axis' unit; give it with " \
        "--set 0x608F:1=VALUE" in refused.stderr.splitlines()[0]
    given = ((0x608F, 1), 1 << 20), ((0x608F, 2), 1)
    twin = eds_twin(str(path), DriveEmulatorConfig(object_values=given))
    assert twin.counts_per_turn == COUNTS_PER_TURN
    wire = Wire(eds=str(path), object_values=given)
    try:
        assert abort_code(wire.read(0x608F, 1)) == 0x06020000  # as the drive: no such object
    finally:
        wire.close()


def test_a_signed_type_where_cia_402_values_are_never_negative_is_taken(tmp_path):
    header = "[608Fsub1]\nParameterName=Encoder increments\nObjectType=0x7\n"
    path = edited(tmp_path, header + "DataType=0x0007", header + "DataType=0x0004")
    assert eds_twin(str(path), DriveEmulatorConfig()).counts_per_turn == COUNTS_PER_TURN
    wrong = edited(tmp_path, "[6064]\nParameterName=Position actual value\nObjectType=0x7\n"
                   "DataType=0x0004", "[6064]\nParameterName=Position actual value\n"
                   "ObjectType=0x7\nDataType=0x0007", "unsigned-position.eds")
    try:
        eds_twin(str(wrong), DriveEmulatorConfig())
    except Exception as exc:  # a position is signed: no relaxation there
        assert "0x6064:0 (Position actual value) is UNSIGNED32, the twin's is INTEGER32" in \
            str(exc)
    else:
        raise AssertionError("an unsigned position was taken")


def test_a_power_on_map_it_cannot_serve_is_left_to_the_master(tmp_path, capsys):
    path = edited(tmp_path, "DefaultValue=0x606C0020", "DefaultValue=0x21000010")
    listed = hil_here(capsys, "emulate", "drive", "--eds", path, cwd=tmp_path)
    assert listed.returncode == 0, listed.stderr
    assert listed.stdout.splitlines()[0].endswith(
        "; power-on maps left for the master to write: TPDO2 (0x1801) (maps 0x2100:0 (DC link "
        "voltage), which the twin cannot produce)")
    wire = Wire(eds=str(path))
    try:
        assert wire.write(0x1801, 1, 0x80000281, "<I")[0] == 0x60  # invalid first
        assert wire.write(0x1A01, 0, 0, "<B")[0] == 0x60
        assert abort_code(wire.write(0x1A01, 1, 0x21000010, "<I")) == 0x06040041
        assert wire.write(0x1A01, 1, 0x606C0020, "<I")[0] == 0x60  # velocity actual: served
    finally:
        wire.close()


def test_a_pdo_invalid_at_power_on_is_not_looked_at(tmp_path):
    text = EX20.read_text()
    rpdo2_map = text.index("[1601sub1]")
    text = text[:rpdo2_map] + text[rpdo2_map:].replace("DefaultValue=0x607A0020",
                                                       "DefaultValue=0x30000020", 1)
    rpdo2 = text.index("[1401sub2]")
    text = text[:rpdo2] + text[rpdo2:].replace("DefaultValue=1", "DefaultValue=252", 1)
    path = tmp_path / "invalid-rpdo2.eds"
    path.write_text(text)
    twin = eds_twin(str(path), DriveEmulatorConfig())
    assert twin.unserved_maps == ()  # RPDO2 is invalid: nothing to say about it


def test_the_deciding_reason_comes_first_then_one_problem_a_line(tmp_path, capsys):
    path = edited(tmp_path, "DefaultValue=0x000002A1", "DefaultValue=0x00000002")
    text = path.read_text().replace(
        "[6077]\nParameterName=Torque actual value\nObjectType=0x7\nDataType=0x0003",
        "[6077]\nParameterName=Torque actual value\nObjectType=0x7\nDataType=0x0004")
    path.write_text(text.replace(EMPTY_RATED, EMPTY_RATED.replace("DefaultValue=2000\n",
                                                                   "DefaultValue=\n")))
    refused = hil_here(capsys, "emulate", "drive", "--eds", path, cwd=tmp_path)
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    lines = refused.stderr.strip().splitlines()
    assert lines[0] == (f"hil: error: EDS {path}: lists no mode hil emulates: 0x6502 = "
                        "0x00000002 (VL); hil emulates PP, PV, HM, CSP, CSV, CST")
    assert [line.partition(": ")[2] for line in lines[1:]] == [
        "0x6075:0 (Motor rated current) has no value: the twin takes the axis' units and "
        "current limits from the file, never its own; give it with --set 0x6075:0=VALUE or "
        "[emulator] set = {\"0x6075:0\" = VALUE} (or a DCF's ParameterValue)",
        "0x6077:0 (Torque actual value) is INTEGER32, the twin's is INTEGER16"]


def test_set_gives_hil_own_dictionary_its_power_on_values_too(tmp_path, capsys):
    wire = Wire(object_values=(((0x6081, 0), 1234),))
    try:
        assert struct.unpack_from("<I", wire.read(0x6081), 4)[0] == 1234
    finally:
        wire.close()
    (tmp_path / "unknown.toml").write_text('[emulator]\nset = {"0x2100:0" = 1}\n')
    refused = hil_here(capsys, "emulate", "drive", "--config", "unknown.toml",
                       "--socketcand", "127.0.0.1:0", cwd=tmp_path)
    assert one_error_line(refused) == "hil: error: set 0x2100:0: hil's drive has no such object"
