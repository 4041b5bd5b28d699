"""CAN frames into hil's drive emulator (SDO server with its segmented and block requests, NMT,
SYNC, RPDOs, heartbeats, any identifier), through the in-process channel a lockstep run uses
(:class:`~hil.emulators.drive.runners.LockstepDrive`): a frame sent there is a frame the node
handles, as in every emulated run.

The rule for the emulator: no frame takes it to an internal error (its EMCY 0x6100 and a
logged traceback), every frame it sends is one a CiA 301 node sends (an SDO answer of 8 bytes
with a known command or abort code, an EMCY of 8 bytes, a heartbeat of 1, its TPDOs), and a
request it refuses with an SDO abort changes no object.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from hypothesis import strategies as st

from hil.emulators.drive.runners import LockstepDrive
from hil.protocols.cia301 import (
    EMCY_BASE,
    EMCY_SOFTWARE,
    HEARTBEAT_BASE,
    SDO_ABORT,
    SDO_ABORT_NAMES,
    SDO_REQUEST_BASE,
    SDO_RESPONSE_BASE,
)
from tests.fuzz.harness import Check, Target, ThreadFailures, bound
from tests.fuzz.strategies import bring_up, node_frames, sdo_write, setting_frames

NODE = 1
#: the server's answers: upload segment, download segment, initiate upload/download, abort
SDO_ANSWERS = (0x00, 0x20, 0x40, 0x60, 0x80)


def check_sent(frame: tuple[int, bytes], tpdo_ids: set[int]) -> None:
    """``frame`` is one the node may send."""
    can_id, data = frame
    if can_id == SDO_RESPONSE_BASE + NODE:
        assert len(data) == 8 and data[0] & 0xE0 in SDO_ANSWERS, f"bad SDO answer {data.hex()}"
        if data[0] == SDO_ABORT:
            code = int.from_bytes(data[4:8], "little")
            assert code in SDO_ABORT_NAMES, f"unknown abort code 0x{code:08X}"
    elif can_id == EMCY_BASE + NODE:
        assert len(data) == 8, f"bad EMCY {data.hex()}"
        assert int.from_bytes(data[:2], "little") != EMCY_SOFTWARE, "an internal error (EMCY)"
    elif can_id == HEARTBEAT_BASE + NODE:
        assert len(data) == 1, f"bad heartbeat {data.hex()}"
    else:
        assert can_id in tpdo_ids and len(data) <= 8, f"frame 0x{can_id:03X} {data.hex()}"


@contextlib.contextmanager
def rig() -> Iterator[Check]:
    """A new lockstep drive for each case; the case's frames sent on the channel one at a
    time, each handled (and the node's time service run) before the next."""
    with ThreadFailures() as failures:
        def check(case: tuple[bool, list[tuple[int, bytes]]]) -> None:
            enabled, frames = case
            drive = LockstepDrive()
            node, bus = drive.node, drive.attach_bus()
            try:
                for frame in (bring_up(NODE) if enabled else []) + frames:
                    before = dict(node.objects.values)
                    with bound(f"frame 0x{frame[0]:03X} {frame[1].hex()}"):
                        bus.send_frames([frame])
                        drive.pump()
                    sent = []
                    while (answer := bus.recv_frame()) is not None:
                        sent.append(answer)
                    failures.check()
                    assert node.internal_errors == 0, f"internal error on {frame}"
                    tpdos = {pdo.cob_id for pdo in node.pdos.pdos if pdo.transmit}
                    for answer in sent:
                        check_sent(answer, tpdos)
                    aborted = any(a[0] == SDO_RESPONSE_BASE + NODE and a[1][:1] == b"\x80"
                                  for a in sent)
                    if frame[0] == SDO_REQUEST_BASE + NODE and aborted:
                        changed = {k for k in before if node.objects.values.get(k) != before[k]}
                        assert not changed, f"{frame[1].hex()} refused, yet changed {changed}"
            finally:
                bus.shutdown()
                drive.close()

        yield check


TARGETS = (
    Target("can-drive-emulator", st.tuples(st.booleans(), st.lists(node_frames(NODE), min_size=4,
                                                                    max_size=30)),
           rig, examples=150),
    Target("can-drive-settings", st.tuples(st.booleans(), st.lists(setting_frames(NODE),
                                                                    min_size=2, max_size=12)),
           rig, examples=100,
           # found: 0x1006 = 4,072,475,500 us taken, the next SYNC stepped the plant 8.1e6 times
           regressions=((False, [(0x601, sdo_write(0x1006, 0, 4, 4_072_475_500)),
                                 (0x080, b"")]),)),
)
