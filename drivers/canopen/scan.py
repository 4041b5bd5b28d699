"""What is on a CAN bus, read without changing anything (``hil drive scan``), in the spirit of
canopen's network scan: the nodes that answer an SDO read of 0x1000, and for each its NMT
state (its heartbeat, if it produces one), CiA 402 state (0x6041) and error code (0x603F), its
position (0x6064 in degrees, scaled by the drive's own 0x608F / 0x6091 as the master scales
it), identity, device type, error register and history, supported modes by name, the current
PDO maps and heartbeat period, optionally the drive's EDS checked for every object hil uses,
and whether hil can drive it as configured (and if not, why). Only SDO uploads are sent: no
NMT command, no SYNC, no write.
"""

from __future__ import annotations

import re
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

from hil.drivers.canopen.config import DriveMasterConfig
from hil.drivers.canopen.current_limit import read_current_limit, unenforced_text
from hil.drivers.canopen.eds import check, import_description, modes_problem
from hil.drivers.canopen.errors import DriveError, DriveLinkLostError
from hil.drivers.canopen.link import Link
from hil.drivers.canopen.objects import DriveObjects
from hil.drivers.canopen.profile import profile_writes
from hil.drivers.canopen.scaling import DriveScaling, read_scaling
from hil.drivers.canopen.sdo import SdoChannel, SdoClient
from hil.protocols.can_frames import Frame
from hil.protocols.cia301 import (
    DEVICE_NAME,
    DEVICE_TYPE,
    ERROR_HISTORY,
    ERROR_REGISTER,
    HEARTBEAT_BASE,
    IDENTITY,
    MAX_NODE_ID,
    NMT_STATE_NAMES,
    PRODUCER_HEARTBEAT,
    RPDO_COMM_BASE,
    RPDO_MAP_BASE,
    SDO_INITIATE_UPLOAD,
    SDO_REQUEST_BASE,
    SDO_RESPONSE_BASE,
    TPDO_COMM_BASE,
    TPDO_MAP_BASE,
    SdoAbortError,
    emcy_text,
)
from hil.protocols.cia402 import (
    CONTROLWORD,
    ERROR_CODE,
    FAULT,
    FAULT_REACTION_ACTIVE,
    MODE_SHORT_NAMES,
    OPERATION_ENABLED,
    OPERATION_MODES,
    PDO_NOT_VALID,
    POSITION_ACTUAL,
    QUICK_STOP_ACTIVE,
    STATUSWORD,
    SUPPORTED_MODES,
    UNKNOWN_STATE,
    VELOCITY_ACTUAL,
    state_of,
    supported_mode_bit,
)

DISCOVER_S = 0.3     # how long answers to the broadcast of SDO requests are collected
HEARTBEAT_S = 1.2    # how long heartbeats are listened to for the NMT states, at most
READ_TIMEOUT_S = 1.0  # one SDO read, as a run's default: a late answer is no silent node
PDOS = 4             # PDOs 1..4 of each direction
UNKNOWN_NMT = "unknown (no heartbeat)"

def mode_names(supported: int) -> list[str]:
    """The modes a 0x6502 value names (``["CSP", "CST"]``); a set bit no mode has is named
    ``bit N``."""
    names, known = [], 0
    for code, short in MODE_SHORT_NAMES.items():
        bit = supported_mode_bit(code)
        known |= bit
        if supported & bit:
            names.append(short)
    return names + [f"bit {b}" for b in range(32) if supported & ~known & (1 << b)]


@dataclass
class PdoReport:
    """One PDO as the node has it configured now; ``entries``: its mapping values."""

    name: str
    cob_id: int
    valid: bool
    transmission: int
    entries: list[int] = field(default_factory=list)

    @property
    def mapped(self) -> list[str]:
        return [f"0x{e >> 16:04X}:{(e >> 8) & 0xFF} ({e & 0xFF} bits)" for e in self.entries]

    def maps(self, index: int, subindex: int) -> bool:
        """Whether this PDO carries object ``index:subindex``."""
        return any(e >> 16 == index and (e >> 8) & 0xFF == subindex for e in self.entries)

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "cob_id": self.cob_id, "valid": self.valid,
                "transmission": self.transmission, "mapped": self.mapped}


@dataclass
class NodeReport:
    """One node as the scan found it; ``problems``: why hil cannot drive it as configured,
    ``notes``: what a run would do first."""

    node_id: int
    mode: str = "cst"
    nmt_state: str = UNKNOWN_NMT
    state: str | None = None             # CiA 402 state of the statusword
    statusword: int | None = None
    error_code: int | None = None        # 0x603F
    error_text: str | None = None
    position_counts: int | None = None   # 0x6064
    position_deg: float | None = None
    scaling: dict[str, Any] | None = None
    scaling_from: dict[str, str] | None = None  # the object, or the key standing in for it
    device_type: int | None = None
    device_name: str | None = None
    identity: dict[str, int] = field(default_factory=dict)
    error_register: int | None = None
    error_history: list[str] = field(default_factory=list)
    supported_modes: int | None = None
    modes: list[str] = field(default_factory=list)
    heartbeat_ms: int | None = None
    pdos: list[PdoReport] = field(default_factory=list)
    eds: dict[str, Any] | None = None    # {"path", "problems"} when checked against an EDS
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def drivable(self) -> bool:
        return not self.problems

    @property
    def verdict(self) -> str:
        """``can drive: yes, in CST`` or ``can drive: no, <every reason>``."""
        if self.problems:
            return "can drive: no, " + "; ".join(self.problems)
        return f"can drive: yes, in {self.mode.upper()}" + "".join(
            f"; {note}" for note in self.notes)

    def as_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["pdos"] = [pdo.as_dict() for pdo in self.pdos]
        return data | {"drivable": self.drivable, "verdict": self.verdict}


def frames_within(link: Link, seconds: float) -> Iterator[Frame]:
    """Every frame heard in the next ``seconds`` (an absolute deadline)."""
    end = time.monotonic() + seconds
    while (remaining := end - time.monotonic()) > 0:
        frame = link.recv(remaining)
        if frame is None:
            return
        yield frame


def discover(link: Link, deadline_s: float = DISCOVER_S) -> list[int]:
    """The nodes that answer an SDO read of 0x1000 (the request sent to every node id at
    once; answers collected for ``deadline_s``)."""
    request = struct.pack("<BHB", SDO_INITIATE_UPLOAD, DEVICE_TYPE, 0) + bytes(4)
    link.send([(SDO_REQUEST_BASE + n, request) for n in range(1, MAX_NODE_ID + 1)])
    found: set[int] = set()
    for can_id, data in frames_within(link, deadline_s):
        node = can_id - SDO_RESPONSE_BASE
        if 1 <= node <= MAX_NODE_ID and len(data) == 8 and data[1:4] == request[1:4]:
            found.add(node)
    return sorted(found)


def heartbeat_window(link: Link, nodes: list[int]) -> float:
    """How long to listen for the heartbeats of ``nodes``: two and a half periods of the
    slowest producer (0x1017), at most :data:`HEARTBEAT_S`; none when no node produces one
    (a node that does not say listened for the whole window)."""
    longest = 0.0
    for node in nodes:
        try:
            period_ms = SdoClient(link, node, READ_TIMEOUT_S, lambda frame: None).read_int(
                PRODUCER_HEARTBEAT, 0, "<H")
        except (DriveError, SdoAbortError):
            return HEARTBEAT_S
        longest = max(longest, period_ms / 1e3)
    return min(HEARTBEAT_S, 2.5 * longest)


def nmt_state_name(data: bytes) -> str:
    """The NMT state a heartbeat's byte carries."""
    return NMT_STATE_NAMES.get(data[0] & 0x7F, f"0x{data[0]:02X}")


def heartbeats(link: Link, listen_s: float = HEARTBEAT_S) -> dict[int, str]:
    """The NMT state each node's heartbeat carries, heard within ``listen_s``."""
    states: dict[int, str] = {}
    for can_id, data in frames_within(link, listen_s):
        node = can_id - HEARTBEAT_BASE
        if 1 <= node <= MAX_NODE_ID and data:
            states[node] = nmt_state_name(data)
    return states


def _optional(read: Any, *args: Any) -> Any:
    try:
        return read(*args)
    except SdoAbortError:
        return None


def read_pdos(sdo: SdoChannel) -> list[PdoReport]:
    """The PDOs 1..4 of each direction the node has, as configured now."""
    read = sdo.read_int
    pdos = []
    for direction, comm_base, map_base in (("RPDO", RPDO_COMM_BASE, RPDO_MAP_BASE),
                                           ("TPDO", TPDO_COMM_BASE, TPDO_MAP_BASE)):
        for k in range(PDOS):
            cob = _optional(read, comm_base + k, 1)
            if cob is None:
                continue
            count = _optional(read, map_base + k, 0, "<B") or 0
            entries = [_optional(read, map_base + k, sub) for sub in range(1, count + 1)]
            pdos.append(PdoReport(
                f"{direction}{k + 1}", cob & 0x7FF, not cob & PDO_NOT_VALID,
                _optional(read, comm_base + k, 2, "<B") or 0,
                [e for e in entries if e is not None]))
    return pdos


def inspect(link: Link, node_id: int, mode: str = "cst", eds: str | None = None,
            config: DriveMasterConfig | None = None) -> NodeReport:
    """Everything :mod:`hil.drivers.canopen.scan` reads of one node, and whether hil can drive it
    in ``mode`` (a name of :data:`~hil.protocols.cia402.OPERATION_MODES`) with ``config``'s
    stand-ins for objects it lacks and its profile, its EDS at ``eds`` checked too when
    given. The deciding reason comes first: the modes it supports."""
    sdo = SdoClient(link, node_id, READ_TIMEOUT_S, lambda frame: None)
    return inspect_drive(sdo, node_id, mode, eds, config, read_pdos)


def inspect_drive(sdo: SdoChannel, node_id: int, mode: str = "cst", eds: str | None = None,
                  config: DriveMasterConfig | None = None,
                  pdos: Callable[[SdoChannel], list[PdoReport]] = lambda sdo: []
                  ) -> NodeReport:
    """:func:`inspect` through any SDO channel (CAN's, or CoE over EtherCAT), its PDOs read by
    ``pdos`` (each transport has its own)."""
    config = config or DriveMasterConfig()
    objects = DriveObjects(sdo)
    read = sdo.read_int
    report = NodeReport(node_id, mode)
    report.device_type = read(DEVICE_TYPE, 0)
    raw_name = _optional(sdo.read, DEVICE_NAME, 0)
    report.device_name = raw_name.decode("latin-1").rstrip("\0") if raw_name else None
    for sub, key in ((1, "vendor_id"), (2, "product_code"), (3, "revision"), (4, "serial")):
        value = _optional(read, IDENTITY, sub)
        if value is not None:
            report.identity[key] = value
    report.error_register = _optional(read, ERROR_REGISTER, 0, "<B")
    count = _optional(read, ERROR_HISTORY, 0, "<B") or 0
    for sub in range(1, min(count, 16) + 1):
        entry = _optional(read, ERROR_HISTORY, sub)
        if entry is not None:
            report.error_history.append(emcy_text(entry & 0xFFFF))
    report.supported_modes = _optional(read, SUPPORTED_MODES, 0)
    if report.supported_modes is not None:
        report.modes = mode_names(report.supported_modes)
    report.heartbeat_ms = _optional(read, PRODUCER_HEARTBEAT, 0, "<H")
    report.pdos = pdos(sdo)
    _read_state(report, sdo)
    scaling = _read_position(report, objects, config)
    if eds is not None:
        _check_eds(report, eds)
    if scaling is not None:
        _check_settings(report, objects, config, scaling)
    report.problems = _problems(report, sdo) + _state_problems(report) + report.problems
    report.notes = _state_notes(report) + report.notes
    return report


def _read_state(report: NodeReport, sdo: SdoChannel) -> None:
    """The CiA 402 state (0x6041) and the error code (0x603F)."""
    report.statusword = _optional(sdo.read_int, STATUSWORD, 0, "<H")
    if report.statusword is not None:
        report.state = state_of(report.statusword)
    report.error_code = _optional(sdo.read_int, ERROR_CODE, 0, "<H")
    if report.error_code is not None:
        report.error_text = emcy_text(report.error_code) if report.error_code else "none"


def _read_position(report: NodeReport, objects: DriveObjects, config: DriveMasterConfig
                   ) -> DriveScaling | None:
    """0x6064 in degrees of the axis, by the drive's own scaling (as the master reads it, the
    config's stand-ins for objects it lacks); the scaling, None when it cannot be had."""
    try:
        scaling, units_from = read_scaling(objects, config.increments_per_rev,
                                           config.rated_current_ma)
    # no or unusable 0x608F / 0x6075: the master would stop too
    except (DriveError, SdoAbortError) as exc:
        reason = re.sub(rf"^drive node {report.node_id}:? ", "", str(exc))
        report.problems.append(f"its position and current cannot be scaled: {reason}")
        return None
    report.scaling, report.scaling_from = scaling.describe(), units_from
    report.position_counts = objects.read(POSITION_ACTUAL, 0, "<i")
    if report.position_counts is not None:
        report.position_deg = scaling.degrees(report.position_counts)
    return scaling


def _check_settings(report: NodeReport, objects: DriveObjects, config: DriveMasterConfig,
                    scaling: DriveScaling) -> None:
    """What a run in the mode would refuse or do without: a limit or a profile value
    configured for an object the drive lacks, a drive that cannot be given the run's limit."""
    mode = OPERATION_MODES[report.mode]
    try:
        limit = read_current_limit(objects, scaling, config.current_limit_ma,
                                   config.max_torque_permille)
        profile_writes(objects, mode, config.profile, scaling)
    except (DriveError, SdoAbortError) as exc:
        report.problems.append(re.sub(rf"^drive node {report.node_id}:? ", "", str(exc)))
        return
    if limit.unenforced:
        report.notes.append(unenforced_text(report.node_id, mode, limit))


def _check_eds(report: NodeReport, path: str) -> None:
    """The EDS at ``path`` against every object hil reads, writes or maps in the mode, and
    against the drive's identity (an EDS of another product describes another drive)."""
    od = import_description(path, report.node_id)
    problems = check(od, OPERATION_MODES[report.mode])
    info = od.device_information
    for key, described in (("vendor_id", info.vendor_number),
                           ("product_code", info.product_number)):
        actual = report.identity.get(key)
        if described is not None and actual is not None and described != actual:
            problems.append(f"is for {key.replace('_', ' ')} 0x{described:X}, the drive "
                            f"says 0x{actual:X} (0x1018)")
    report.eds = {"path": path, "problems": problems}
    report.problems += [f"EDS {path}: {problem}" for problem in problems]


def _state_problems(report: NodeReport) -> list[str]:
    """What its CiA 402 state stands in the way of: a fault to clear first."""
    state = report.state
    if state in (FAULT, FAULT_REACTION_ACTIVE):
        code = f" ({report.error_text})" if report.error_code else ""
        return [f"in {state}{code}, `hil drive reset` clears it"]
    if state == UNKNOWN_STATE:
        return [f"statusword 0x{report.statusword:04X} is no CiA 402 state"]
    return []


def _state_notes(report: NodeReport) -> list[str]:
    """What a run does first because of its CiA 402 state: an enabled drive is disabled."""
    if report.state in (OPERATION_ENABLED, QUICK_STOP_ACTIVE):
        return [f"it is in {report.state} now (another master?): a run disables voltage first"]
    return []


def _problems(report: NodeReport, sdo: SdoChannel) -> list[str]:
    """Whether the node is a CiA 402 drive that supports the mode (the deciding reasons,
    first), and has the objects of the cyclic exchange in it."""
    problems = []
    mode = OPERATION_MODES[report.mode]
    if report.supported_modes is not None and \
            (problem := modes_problem(report.supported_modes, mode)) is not None:
        problems.append(problem)
    if report.device_type is not None and report.device_type & 0xFFFF != 402:
        problems.append(f"not a CiA 402 drive (device type 0x{report.device_type:08X})")
    target = () if mode.set_point is None else ((mode.set_point[0], "the mode's target"),)
    for index, what in ((CONTROLWORD, "controlword"), (STATUSWORD, "statusword"),
                        (POSITION_ACTUAL, "position actual"), (VELOCITY_ACTUAL, "velocity actual"),
                        *target):
        try:
            sdo.read(index, 0)
        except SdoAbortError as exc:
            problems.append(f"0x{index:04X} {what}: {exc}")
    return problems


def scan(link: Link, nodes: list[int] | None = None, mode: str = "cst",
         eds: str | None = None, config: DriveMasterConfig | None = None) -> list[NodeReport]:
    """The nodes of ``link`` (``nodes``: these only), each inspected (against the EDS at
    ``eds`` too, with ``config``'s stand-ins and profile); a node that does not answer at all
    is reported as such."""
    found = discover(link) if nodes is None else nodes
    states = heartbeats(link, heartbeat_window(link, found)) if found else {}
    reports = []
    for node in found:
        try:
            report = inspect(link, node, mode, eds, config)
        except DriveLinkLostError:
            report = NodeReport(node, mode, problems=["does not answer SDO"])
        # refused, or an answer that makes no sense (wrong size, bad command)
        except (DriveError, SdoAbortError) as exc:
            report = NodeReport(node, mode, problems=[str(exc)])
        if node in states:
            report.nmt_state = states[node]
        reports.append(report)
    return reports
