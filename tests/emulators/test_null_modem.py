"""The null-modem cable (two real pseudo-terminals) and the noisy line it plays: bytes flipped
at the asked rate, one bit each, both ways, only inside the fault's window, the same flips for
the same seed; a bad noise spec is one line."""

from __future__ import annotations

import math

import pytest
import serial

from hil.emulators.errors import EmulatorSetupError
from hil.emulators.faults import parse_fault
from hil.emulators.null_modem import NullModem

pytestmark = [pytest.mark.timeout(60)]

DATA = bytes(range(256)) * 40  # 10240 bytes


def carry(modem: NullModem, way: int, data: bytes = DATA) -> bytes:
    """``data`` written at one end of ``modem`` (ports[0] for way 0), as read at the other."""
    source, sink = (modem.ports[0], modem.ports[1]) if way == 0 else modem.ports[::-1]
    with serial.Serial(source, timeout=5) as a, serial.Serial(sink, timeout=5) as b:
        got = b""
        for i in range(0, len(data), 512):  # a chunk at a time: the pty's buffer is small
            a.write(data[i:i + 512])
            got += b.read(len(data[i:i + 512]))
    return got


def flipped_bits(sent: bytes, got: bytes) -> list[int]:
    """Per byte that differs: how many bits differ."""
    return [bin(x ^ y).count("1") for x, y in zip(sent, got, strict=True) if x != y]


@pytest.mark.parametrize("way", [0, 1])
def test_a_noisy_line_flips_one_bit_of_the_asked_share_of_bytes_each_way(way):
    with NullModem(faults=[parse_fault("noise@0:rate=0.02,seed=3")]) as modem:
        got = carry(modem, way)
    bits = flipped_bits(DATA, got)
    n, p = len(DATA), 0.02
    assert abs(len(bits) - n * p) < 5 * math.sqrt(n * p * (1 - p))  # 5 sigma: 205 +- 71
    assert set(bits) == {1}  # one bit per flipped byte
    assert modem.flipped[way] == len(bits) and modem.carried[way] == n
    assert modem.flipped[1 - way] == modem.carried[1 - way] == 0
    assert modem.faults.hits == {"noise@0:rate=0.02,seed=3": len(bits)}


def test_the_same_seed_flips_the_same_bytes_and_another_seed_others():
    runs = {}
    for seed in (1, 1, 2):
        with NullModem(faults=[parse_fault(f"noise@0:rate=0.01,seed={seed}")]) as modem:
            runs.setdefault(seed, []).append(carry(modem, 0))
    assert runs[1][0] == runs[1][1] != DATA
    assert runs[2][0] != runs[1][0]


def test_outside_its_window_the_line_is_clean():
    with NullModem(faults=[parse_fault("noise@30:rate=1")]) as modem:
        assert carry(modem, 1) == DATA
    assert modem.flipped == [0, 0] and modem.faults.events == []


@pytest.mark.parametrize(("spec", "why"), [
    ("noise@0", "noise needs rate="),
    ("noise@0:rate=0", "rate = 0.0 is not valid (fraction of the bytes flipped"),
    ("noise@0:rate=1.5", "rate = 1.5 is not valid"),
    ("noise@0:rate=0.1,seed=x", "seed: 'x' is not an integer"),
])
def test_a_bad_noise_spec_is_one_line(spec, why):
    with pytest.raises(EmulatorSetupError) as err:
        parse_fault(spec)
    assert why in str(err.value) and "\n" not in str(err.value)


def test_a_line_plays_line_faults_only():
    with pytest.raises(EmulatorSetupError, match="a bench emulator fault, not one the line"):
        NullModem(faults=[parse_fault("drop@0")])
