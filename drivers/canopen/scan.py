"""What is on a CAN bus, read without changing anything (``hil drive scan``), in the spirit of
canopen's network scan: the nodes that answer an SDO read of 0x1000, and for each its NMT
state (its heartbeat, if it produces one), identity, device type, error register and history,
supported modes, the current PDO maps and heartbeat period, and whether hil can drive it as
configured (and if not, why). Only SDO uploads are sent: no NMT command, no SYNC, no write.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

from drivers.can_frames import Frame
from drivers.canopen.errors import DriveError, DriveLinkLostError, SdoAbortError
from drivers.canopen.link import Link
from drivers.canopen.sdo import SdoClient
from drivers.cia301 import (
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
    emcy_text,
)
from drivers.cia402 import ENCODER_RESOLUTION, MODES, PDO_NOT_VALID, SUPPORTED_MODE_BITS

DISCOVER_S = 0.3     # how long answers to the broadcast of SDO requests are collected
HEARTBEAT_S = 1.2    # how long heartbeats are listened to for the NMT states
READ_TIMEOUT_S = 0.3
PDOS = 4             # PDOs 1..4 of each direction


@dataclass
class PdoReport:
    """One PDO as the node has it configured now."""

    name: str
    cob_id: int
    valid: bool
    transmission: int
    mapped: list[str]


@dataclass
class NodeReport:
    """One node as the scan found it; ``problems``: why hil cannot drive it as configured."""

    node_id: int
    nmt_state: str = "unknown (no heartbeat)"
    device_type: int | None = None
    device_name: str | None = None
    identity: dict[str, int] = field(default_factory=dict)
    error_register: int | None = None
    error_history: list[str] = field(default_factory=list)
    supported_modes: int | None = None
    heartbeat_ms: int | None = None
    pdos: list[PdoReport] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def drivable(self) -> bool:
        return not self.problems

    def as_dict(self) -> dict[str, Any]:
        return asdict(self) | {"drivable": self.drivable}


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


def heartbeats(link: Link, listen_s: float = HEARTBEAT_S) -> dict[int, str]:
    """The NMT state each node's heartbeat carries, heard within ``listen_s``."""
    states: dict[int, str] = {}
    for can_id, data in frames_within(link, listen_s):
        node = can_id - HEARTBEAT_BASE
        if 1 <= node <= MAX_NODE_ID and data:
            states[node] = NMT_STATE_NAMES.get(data[0] & 0x7F, f"0x{data[0]:02X}")
    return states


def _optional(read: Any, *args: Any) -> Any:
    try:
        return read(*args)
    except SdoAbortError:
        return None


def inspect(link: Link, node_id: int, mode: str = "cst") -> NodeReport:
    """Everything :mod:`drivers.canopen.scan` reads of one node, and whether hil can drive it
    in ``mode`` (``cst`` or ``csp``)."""
    sdo = SdoClient(link, node_id, READ_TIMEOUT_S, lambda frame: None)
    read = sdo.read_int
    report = NodeReport(node_id)
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
    report.supported_modes = _optional(read, 0x6502, 0)
    report.heartbeat_ms = _optional(read, PRODUCER_HEARTBEAT, 0, "<H")
    for direction, comm_base, map_base in (("RPDO", RPDO_COMM_BASE, RPDO_MAP_BASE),
                                           ("TPDO", TPDO_COMM_BASE, TPDO_MAP_BASE)):
        for k in range(PDOS):
            cob = _optional(read, comm_base + k, 1)
            if cob is None:
                continue
            entries = [_optional(read, map_base + k, sub)
                       for sub in range(1, (_optional(read, map_base + k, 0, "<B") or 0) + 1)]
            report.pdos.append(PdoReport(
                f"{direction}{k + 1}", cob & 0x7FF, not cob & PDO_NOT_VALID,
                _optional(read, comm_base + k, 2, "<B") or 0,
                [f"0x{e >> 16:04X}:{(e >> 8) & 0xFF} ({e & 0xFF} bits)"
                 for e in entries if e is not None]))
    report.problems = _problems(report, sdo, mode)
    return report


def _problems(report: NodeReport, sdo: SdoClient, mode: str) -> list[str]:
    problems = []
    if report.device_type is not None and report.device_type & 0xFFFF != 402:
        problems.append(f"not a CiA 402 drive (device type 0x{report.device_type:08X})")
    bit = SUPPORTED_MODE_BITS[MODES[mode]]
    if report.supported_modes is None:
        problems.append("no 0x6502 (supported modes)")
    elif not report.supported_modes & bit:
        problems.append(f"mode {mode.upper()} not supported (0x6502 = "
                        f"0x{report.supported_modes:08X})")
    increments = _optional(sdo.read_int, ENCODER_RESOLUTION, 1)
    if not increments:
        problems.append("no encoder resolution 0x608F: positions cannot be scaled")
    for index, what in ((0x6075, "rated current"), (0x6040, "controlword"),
                        (0x6041, "statusword"), (0x6064, "position actual"),
                        (0x606C, "velocity actual"), (0x6077, "torque actual"),
                        (0x6071 if mode == "cst" else 0x607A, "the mode's target")):
        try:
            sdo.read(index, 0)
        except SdoAbortError as exc:
            problems.append(f"0x{index:04X} {what}: {exc}")
    return problems


def scan(link: Link, nodes: list[int] | None = None, mode: str = "cst"
         ) -> list[NodeReport]:
    """The nodes of ``link`` (``nodes``: these only), each inspected; a node that does not
    answer at all is reported as such."""
    found = discover(link) if nodes is None else nodes
    states = heartbeats(link) if found else {}
    reports = []
    for node in found:
        try:
            report = inspect(link, node, mode)
        except DriveLinkLostError:
            report = NodeReport(node, problems=["does not answer SDO"])
        except DriveError as exc:
            report = NodeReport(node, problems=[str(exc)])
        if node in states:
            report.nmt_state = states[node]
        reports.append(report)
    return reports
