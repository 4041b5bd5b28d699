"""CAN frames into hil's CiA 402 master (SDO answers, EMCY, heartbeats, TPDOs): the master
against the emulated drive in lockstep, as every ``emulated`` run has it, with the frames it
receives damaged on their way (the data's bits flipped, cut, grown or replaced, the
identifier changed, a frame dropped, a stray frame slipped in) while it opens, configures and
enables the drive, runs cycles and closes.

The rule for the master: each step works or raises a :class:`~hil.errors.HilError` of one
line (a DriveError, an SDO abort), within the bound; ``close()`` never raises; and once it
has closed, the drive is not left in OPERATION ENABLED (its safe state was requested).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from hypothesis import strategies as st

from hil.protocols.can_frames import Frame
from hil.protocols.cia402 import OPERATION_ENABLED
from hil.servo.config import load_drive_config
from hil.servo.rig import EmulatedDrive
from tests.fuzz.harness import Check, Target, bound, clear_error
from tests.fuzz.strategies import flip

CYCLES = 12
#: a faster SDO time-out than the packaged 1 s: in lockstep a dropped answer waits it out on
#: the wall clock (a faster device; nothing else changes)
OVERRIDES = {"master": {"sdo_timeout_ms": 20}}
#: what the drive sends: the ids a damaged frame is given
DRIVE_IDS = (0x581, 0x081, 0x701, 0x181, 0x281, 0x000, 0x080, 0x77F)


@dataclass(frozen=True)
class Noise:
    """What happens to one received frame."""

    kind: str          # keep, flip, cut, grow, replace, relabel, drop, stray
    data: bytes = b""  # the bits flipped (flip), bytes added or put (grow, replace, stray)
    can_id: int = 0    # the new identifier (relabel, stray)

    def apply(self, frame: Frame) -> list[Frame]:
        can_id, data = frame
        if self.kind == "flip":
            return [(can_id, flip(data, list(self.data[::2]), list(self.data[1::2])))]
        if self.kind == "cut":
            return [(can_id, data[:len(self.data) % 8])]
        if self.kind == "grow":
            return [(can_id, (data + self.data)[:8])]
        if self.kind == "replace":
            return [(can_id, self.data[:8])]
        if self.kind == "relabel":
            return [(self.can_id, data)]
        if self.kind == "drop":
            return []
        if self.kind == "stray":
            return [(self.can_id, self.data[:8]), frame]
        return [frame]


NOISE = st.builds(Noise, st.sampled_from(["keep", "flip", "flip", "cut", "grow", "replace",
                                          "relabel", "drop", "stray"]),
                  st.binary(max_size=8), st.sampled_from(DRIVE_IDS) | st.integers(0, 0x7FF))


class NoisyReceive:
    """The master's receive with the plan's noise on the frames after the first ``skip``."""

    def __init__(self, receive: Callable[[float | None], Frame | None], skip: int,
                 plan: list[Noise]) -> None:
        self._receive, self._skip, self._plan = receive, skip, list(plan)
        self._ready: list[Frame] = []

    def __call__(self, timeout: float | None = None) -> Frame | None:
        while not self._ready:
            frame = self._receive(timeout)
            if frame is None:
                return None
            if self._skip:
                self._skip -= 1
                return frame
            self._ready = self._plan.pop(0).apply(frame) if self._plan else [frame]
        return self._ready.pop(0)


@contextlib.contextmanager
def rig() -> Iterator[Check]:
    config = load_drive_config(overrides=OVERRIDES)

    def check(case: tuple[int, list[Noise]]) -> None:
        skip, plan = case
        master = EmulatedDrive(config.master, config.emulator)
        # the noise sits between the bus and the master's link (python-can's frames intact)
        master.link._recv_frame = NoisyReceive(master.link._recv_frame, skip, plan)
        node = master.emulator.node
        with bound("the master against a noisy drive"):
            try:
                master.start()
                for k in range(CYCLES):
                    master.exchange(50.0 * (k % 3 - 1))
            except Exception as exc:
                clear_error(exc)
            finally:
                master.close()
        assert node.state != OPERATION_ENABLED, \
            "the master closed and left its drive in OPERATION ENABLED"

    yield check


TARGETS = (
    # the master receives ~58 frames to start, ~24 in its cycles, ~5 to stop: the noise
    # starts anywhere among them
    Target("can-master", st.tuples(st.integers(0, 90), st.lists(NOISE, min_size=1,
                                                                max_size=10)),
           rig, examples=60,
           regressions=(
               (2, [Noise("flip", b"\x04\x00")]),  # a statusword bit: a wait, the drive's SYNCs
               (0, [Noise("relabel", can_id=0x000)]),  # another master: the stop was cancelled
               (52, [Noise("cut")]),  # the enable's answer lost: the drive left enabled
               # a TPDO1 that says FAULT REACTION ACTIVE: the drive dropped without a stop
               (56, [Noise("keep"), Noise("keep"), Noise("replace", b"\x0f\x00" + bytes(4))]),
           )),
)
