"""The pieces of ``hil drive sdo`` and ``hil drive scan`` that need no bus: object addresses,
type names, values encoded as canopen decodes them, and 0x6502 read by name against canopen's
own table of the CiA 402 modes."""

import pytest
from canopen.objectdictionary import ODVariable, datatypes
from canopen.profiles.p402 import OperationMode

from hil.drivers.canopen.scan import mode_names
from hil.drivers.canopen.sdo_tool import ObjectValue, encode, parse_object, parse_type
from hil.drivers.errors import DriverSetupError


@pytest.mark.parametrize(("text", "expected"), [
    ("0x6041", (0x6041, 0)), ("6041", (0x6041, 0)), ("0x1018:4", (0x1018, 4)),
    ("1A00:0x02", (0x1A00, 2)), ("0x1600:10", (0x1600, 10)),
])
def test_objects_are_a_hex_index_and_a_sub_index(text, expected):
    assert parse_object(text) == expected


@pytest.mark.parametrize("text", ["", "0x6041:", "x", "0x10000", "0x6041:256", "0x6041:-1"])
def test_a_bad_object_says_the_form(text):
    with pytest.raises(ValueError, match=r"INDEX\[:SUB\]|index is 0x0000..0xFFFF"):
        parse_object(text)


def test_short_and_cia_type_names_are_canopens_codes():
    assert parse_type("u16") == parse_type("UNSIGNED16") == parse_type("unsigned16") \
        == datatypes.UNSIGNED16
    assert parse_type("i32") == datatypes.INTEGER32 and parse_type("str") == \
        datatypes.VISIBLE_STRING
    with pytest.raises(ValueError, match="unknown type 'u12'"):
        parse_type("u12")


@pytest.mark.parametrize(("text", "kind", "value"), [
    ("-1", datatypes.INTEGER16, -1), ("0x8000", datatypes.UNSIGNED16, 0x8000),
    ("2147483647", datatypes.INTEGER32, 2**31 - 1), ("true", datatypes.BOOLEAN, True),
    ("1.5", datatypes.REAL32, 1.5),
])
def test_values_encode_as_canopen_decodes_them(text, kind, value):
    var = ODVariable("x", 0x2000, 0)
    var.data_type = kind
    assert var.decode_raw(encode(text, kind)) == value


@pytest.mark.parametrize(("text", "kind", "message"), [
    ("65536", datatypes.UNSIGNED16, r"not a valid UNSIGNED16 \(0..65535\)"),
    ("-129", datatypes.INTEGER8, r"not a valid INTEGER8 \(-128..127\)"),
    ("ten", datatypes.UNSIGNED8, "'ten' is not a valid UNSIGNED8"),
])
def test_a_value_that_does_not_fit_its_type_is_one_line(text, kind, message):
    with pytest.raises(DriverSetupError, match=message):
        encode(text, kind)


def test_a_read_typed_wrong_for_its_size_is_one_line_and_an_untyped_one_unsigned():
    with pytest.raises(DriverSetupError, match=r"0x6064:0 has 4 bytes .*, UNSIGNED16 is 2"):
        ObjectValue(1, 0x6064, 0, bytes(4), datatypes.UNSIGNED16)
    untyped = ObjectValue(1, 0x6041, 0, b"\x50\x02", None)
    assert untyped.value == 0x0250 and untyped.type_name is None
    assert ObjectValue(1, 0x1008, 0, b"abc", None).value is None  # 3 bytes: no unsigned


def test_every_mode_bit_is_named_as_canopen_numbers_it():
    for code, short in [(8, "CSP"), (10, "CST"), (1, "PP"), (6, "HM")]:
        bit = OperationMode.SUPPORTED[OperationMode.CODE2NAME[code]]
        assert mode_names(bit) == [short]
    assert mode_names(0x0280) == ["CSP", "CST"]
    assert mode_names(0x0000_0400 | 0x0001_0000) == ["bit 10", "bit 16"]  # none of these
    assert mode_names(0) == []
