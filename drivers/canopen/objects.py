"""Which objects a drive has, found out once per object: from its EDS or DCF when the master
was given one (an object the file lacks is not asked for), else by SDO. Either way a drive
that answers an upload with abort 0x06020000 (no such object) or 0x06090011 (no such
sub-index) has not got it. An object a drive lacks is neither read nor written: its value
comes from the configuration, or hil does without it and says so (:mod:`.master`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from hil.drivers.canopen.errors import DriveError
from hil.drivers.canopen.sdo import SdoChannel
from hil.protocols.cia301 import (
    ABORT_NO_OBJECT,
    ABORT_NO_SUBINDEX,
    CONSUMER_HEARTBEAT,
    CYCLE_PERIOD,
    PRODUCER_HEARTBEAT,
    SdoAbortError,
)
from hil.protocols.cia402 import ERROR_CODE, QUICK_STOP_OPTION, SUPPORTED_MODES, TORQUE_ACTUAL

ABSENT = (ABORT_NO_OBJECT, ABORT_NO_SUBINDEX)
#: the optional objects hil does without, by (index, sub-index): what each is, and how
DOING_WITHOUT: dict[tuple[int, int], tuple[str, str]] = {
    (SUPPORTED_MODES, 0): ("supported drive modes", "the mode is checked by 0x6061 alone"),
    (ERROR_CODE, 0): ("error code", "a fault is named by its last EMCY"),
    (CYCLE_PERIOD, 0): ("communication cycle period", "the drive is not told the SYNC period"),
    (PRODUCER_HEARTBEAT, 0): ("producer heartbeat time", "the master watches the drive's "
                              "TPDOs alone, not a heartbeat"),
    (CONSUMER_HEARTBEAT, 1): ("consumer heartbeat time", "the drive does not watch the "
                              "master's heartbeat"),
    (QUICK_STOP_OPTION, 0): ("quick stop option code", "its own quick stop applies, not "
                             "[master] quick_stop_option"),
    (TORQUE_ACTUAL, 0): ("torque actual value", "its current is not measured: /drive/feedback "
                         "has current_mA NaN"),
}


def without_text(node_id: int, index: int, subindex: int) -> str:
    """``drive node N has no 0x1006 (communication cycle period): the drive is not told
    ...``: one of :data:`DOING_WITHOUT`, said of a drive."""
    title, how = DOING_WITHOUT[index, subindex]
    name = f"0x{index:04X}" + (f":{subindex}" if subindex else "")
    return f"drive node {node_id} has no {name} ({title}): {how}"


def described(od: Any, index: int, subindex: int) -> bool:
    """Whether the object dictionary ``od`` (canopen's, from an EDS or DCF) has
    ``index:subindex`` (a plain variable has sub-index 0 only)."""
    if index not in od:
        return False
    obj = od[index]
    if hasattr(obj, "subindices"):
        return subindex in obj.subindices
    return subindex == 0


class DriveObjects:
    """The objects of one drive, by its SDO client and, when given, its description ``od``
    (canopen's object dictionary of its EDS or DCF)."""

    def __init__(self, sdo: SdoChannel, od: Any = None) -> None:
        self.sdo, self.od = sdo, od
        self._has: dict[tuple[int, int], bool] = {}

    def has(self, index: int, subindex: int = 0) -> bool:
        """Whether the drive has ``index:subindex``: its description says, else one upload
        (an abort other than "does not exist", write-only say, is an object that exists)."""
        key = (index, subindex)
        if key not in self._has:
            if self.od is not None and not described(self.od, index, subindex):
                self._has[key] = False
            else:
                try:
                    self.sdo.read(index, subindex)
                    self._has[key] = True
                except SdoAbortError as exc:
                    self._has[key] = exc.code not in ABSENT
        return self._has[key]

    def read(self, index: int, subindex: int = 0, fmt: str = "<I") -> int | None:
        """The object's value; None when the drive has not got it. Any other refusal
        raises."""
        if self._has.get((index, subindex)) is False or (
                self.od is not None and not described(self.od, index, subindex)):
            self._has[(index, subindex)] = False
            return None
        try:
            value = self.sdo.read_int(index, subindex, fmt)
        except SdoAbortError as exc:
            if exc.code not in ABSENT:
                raise
            self._has[(index, subindex)] = False
            return None
        self._has[(index, subindex)] = True
        return value



@dataclass(frozen=True)
class StandIn:
    """A ``[master]`` key that stands in for an object a drive lacks: the object, what it
    holds (with its unit) and the key."""

    index: int
    subindex: int
    what: str
    key: str

    @property
    def name(self) -> str:
        return f"0x{self.index:04X}" + (f":{self.subindex}" if self.subindex else "")

    def missing(self, node_id: int) -> DriveError:
        """Neither the drive nor the configuration has a value the run needs."""
        return DriveError(f"drive node {node_id} has no {self.name} ({self.what}): set "
                          f"[master] {self.key} to its value")


def drive_or_config(objects: DriveObjects, stand_in: StandIn, configured: float | None,
                    fmt: str = "<I") -> tuple[float | None, str]:
    """The value of ``stand_in``'s object and where it came from: the drive's (its object's
    name), else the key's (``configured``; None: neither has one). A key set for a drive
    that has the object, to another value, is refused: it could not take effect."""
    value = objects.read(stand_in.index, stand_in.subindex, fmt)
    if value is None:
        return configured, f"[master] {stand_in.key}"
    if configured is not None and configured != value:
        raise DriveError(f"drive node {objects.sdo.node_id}: [master] {stand_in.key} = "
                         f"{configured:g} stands in for {stand_in.name} ({stand_in.what}) on a "
                         f"drive without it, and this drive has it: {value}; drop the key")
    return value, stand_in.name


class Notices:
    """What a run does differently because of the drive (an object it lacks, a limit it cannot
    be given): each told once, as a warning event through ``event(kind, message, level)``
    and as a line the person at the terminal must read (:meth:`take`)."""

    def __init__(self, event: Callable[..., None]) -> None:
        self._event = event
        self._told: set[str] = set()
        self._pending: list[str] = []

    def tell(self, kind: str, message: str) -> None:
        if message not in self._told:
            self._told.add(message)
            self._pending.append(message)
            self._event(kind, message, level="warning")

    def take(self) -> list[str]:
        """The lines not taken yet (the events are recorded already)."""
        pending, self._pending = self._pending, []
        return pending
