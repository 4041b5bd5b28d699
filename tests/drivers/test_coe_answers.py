"""What hil's CoE SDO client takes as a confirmed download: the command specifier, not the
bits CiA 301 reserves beside it (KickCAT's simulated slave echoes the request's size bits)."""

import pytest

from hil.drivers.ethercat.coe import download_confirmed


@pytest.mark.parametrize("command", [0x60, 0x6B, 0x6F, 0x63])
def test_a_download_response_is_confirmed_whatever_its_reserved_bits(command):
    assert download_confirmed(command)


@pytest.mark.parametrize("command", [0x40, 0x43, 0x80, 0x20, 0x00, 0xE0])
def test_other_answers_to_a_download_are_not(command):
    assert not download_confirmed(command)
