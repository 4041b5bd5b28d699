"""A drive's identity (0x1018) and how hil tells its own emulator from a vendor's drive."""

from hil.drivers.canopen.identity import HIL_EMULATOR, Identity, not_hil_emulator
from hil.emulators.drive.od import build_object_dictionary


def test_hils_emulator_is_told_by_the_identity_its_dictionary_gives():
    identity = build_object_dictionary(5)[0x1018]
    assert (identity[1].default, identity[2].default) == HIL_EMULATOR
    assert Identity(*HIL_EMULATOR, 1, 5).hil_emulator


def test_any_other_identity_is_a_vendors_drive():
    assert not Identity(0x00C0FFEE, 0x402).hil_emulator
    assert not Identity(0, 0x403).hil_emulator
    assert not Identity().hil_emulator  # a drive without 0x1018:2 says nothing
    assert Identity(0xC0FFEE, None, 3).text() == "vendor 0xC0FFEE, revision 0x3"
    assert Identity().text() == "no identity"
    why = not_hil_emulator(3, Identity(0xC0FFEE, 17), "0x2005 time base")
    assert why.startswith("drive node 3 is not hil's drive emulator (0x1018: vendor 0xC0FFEE, "
                          "product 0x11): ") and "(0x2005 time base)" in why
