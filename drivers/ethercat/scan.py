"""``hil drive scan ethercat://IFACE``: every slave of the segment as SOEM's scan finds it
(its position, name and identity from the SII, its AL state), then the CAN scan's inspection of
the drive through CoE (:func:`~hil.drivers.canopen.scan.inspect_drive`: CiA 402 state, error
code, position, modes, whether hil can drive it and if not why), with the PDOs the slave has
assigned to its SyncManagers (0x1C12 outputs, 0x1C13 inputs) and what each maps. Read-only."""

from __future__ import annotations

from collections.abc import Callable

from hil.drivers.canopen.config import DriveMasterConfig
from hil.drivers.canopen.errors import DriveError, DriveLinkLostError
from hil.drivers.canopen.scan import NodeReport, PdoReport, inspect_drive
from hil.drivers.canopen.sdo import SdoChannel
from hil.drivers.ethercat.coe import CoeSdo
from hil.drivers.ethercat.segment import Segment
from hil.protocols.cia301 import SdoAbortError
from hil.protocols.ethercat import RXPDO_ASSIGN, TXPDO_ASSIGN, al_state_text

READ_TIMEOUT_S = 0.5
MAX_ASSIGNED = 8


def assigned_pdos(sdo: SdoChannel) -> list[PdoReport]:
    """The PDOs assigned to the outputs (0x1C12) and inputs (0x1C13), each with its mapping."""
    pdos = []
    for assign, direction in ((RXPDO_ASSIGN, "RxPDO"), (TXPDO_ASSIGN, "TxPDO")):
        try:
            count = sdo.read_int(assign, 0, "<B")
        except SdoAbortError:
            continue
        for sub in range(1, min(count, MAX_ASSIGNED) + 1):
            mapping = sdo.read_int(assign, sub, "<H")
            entries = [sdo.read_int(mapping, entry)
                       for entry in range(1, sdo.read_int(mapping, 0, "<B") + 1)]
            pdos.append(PdoReport(f"{direction} 0x{mapping:04X} (0x{assign:04X}:{sub})", 0,
                                  True, 0, entries))
    return pdos


def scan_segment(segment: Segment, positions: list[int] | None = None, mode: str = "cst",
                 eds: str | None = None, config: DriveMasterConfig | None = None,
                 on_emergency: Callable[[bytes], None] = lambda data: None
                 ) -> list[NodeReport]:
    """Each slave of ``segment`` (``positions``: these only) inspected as a drive; a slave
    that does not answer CoE is reported as such."""
    found = positions or list(range(1, len(segment.slaves) + 1))
    reports = []
    for position in found:
        slave = segment.slave(position)
        sdo = CoeSdo(segment, position, position, READ_TIMEOUT_S, on_emergency)
        try:
            report = inspect_drive(sdo, position, mode, eds, config, assigned_pdos)
        except DriveLinkLostError:
            report = NodeReport(position, mode, problems=["does not answer CoE SDO"])
        except (DriveError, SdoAbortError) as exc:
            report = NodeReport(position, mode, problems=[str(exc)])
        status, _ = segment.al_status(position)
        report.nmt_state = f"AL {al_state_text(status)}"
        report.device_name = report.device_name or slave.name
        sii = {"vendor_id": slave.man, "product_code": slave.id, "revision": slave.rev}
        report.identity = {**sii, **report.identity}
        reports.append(report)
    return reports
