"""An emulated CiA 402 drive on EtherCAT: the ESC skin (:mod:`~hil.emulators.ethercat.esc`)
over the same drive as the CAN emulator (:class:`~hil.emulators.drive.node.DriveNode`: its
object dictionary or a twin's, state machine, modes, plant, faults, models).

What is EtherCAT's own lives here: the SII (hil's defaults from the drive's identity and PDO
maps, or a vendor's ESI file), the CoE mailbox in front of the drive's objects, the
SyncManager objects (0x1C00 communication types; 0x1C12 / 0x1C13 the PDOs assigned to the
outputs and inputs, written in PRE-OP only, as the PDO mappings are), the AL state as the
drive's NMT state (OP: outputs applied; an SDO write of an object they carry is stored only,
and their next cycle overwrites it, as on a vendor's drive), and the process-data cycle: each
one advances the drive one communication cycle, as a SYNC does on CAN (in lockstep the
master's cycles are the drive's time). The drive's emergencies go out as CoE emergencies;
its CAN frames (TPDOs, heartbeats) have no wire here and are dropped.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable

from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.node import DriveNode
from hil.emulators.drive.pdo import Pdo
from hil.emulators.ethercat.assignment import Assignment
from hil.emulators.ethercat.coe import CoeServer, emergency
from hil.emulators.ethercat.esc import Esc
from hil.emulators.ethercat.sii import PdoEntrySpec, PdoSpec, SiiContent, build_sii
from hil.emulators.faults import Fault
from hil.protocols.can_frames import Frame
from hil.protocols.cia301 import (
    ABORT_DEVICE_STATE,
    ABORT_NO_SUBINDEX,
    ABORT_READ_ONLY,
    DEVICE_NAME,
    EMCY_BASE,
    IDENTITY,
    SdoAbortError,
)
from hil.protocols.cia402 import PDO_NOT_VALID
from hil.protocols.ethercat import (
    OP,
    PRE_OP,
    RXPDO_ASSIGN,
    RXPDO_MAPPINGS,
    SAFE_OP,
    SM_COMM_TYPES,
    SM_TYPE_INPUTS,
    SM_TYPE_MAILBOX_IN,
    SM_TYPE_MAILBOX_OUT,
    SM_TYPE_OUTPUTS,
    TXPDO_ASSIGN,
    TXPDO_MAPPINGS,
)

SM_TYPES = (SM_TYPE_MAILBOX_OUT, SM_TYPE_MAILBOX_IN, SM_TYPE_OUTPUTS, SM_TYPE_INPUTS)
DEFAULT_ASSIGNMENT = {RXPDO_ASSIGN: (0x1600,), TXPDO_ASSIGN: (0x1A00, 0x1A01)}


class EthercatDrive:
    """One emulated drive as an EtherCAT slave (an
    :class:`~hil.emulators.ethercat.esc.EscApplication`); ``last``: the end of the line;
    ``sii``: what its EEPROM says (None: hil's defaults from its dictionary)."""

    def __init__(self, config: DriveEmulatorConfig | None = None, *, clock: str = "auto",
                 faults: Iterable[Fault] = (), on_fault: Callable[[str], None] | None = None,
                 sii: SiiContent | None = None, pdos_from_sii: bool = False,
                 last: bool = True) -> None:
        self._messages: list[bytes] = []
        self.node = DriveNode(config, send=self._from_drive, clock=clock, faults=faults,
                              on_fault=on_fault)
        self._free_mappings()
        content = sii or default_sii(self.node)
        self.sii = content
        # the PDOs the node has, with their rules: the SII's where they are its (a twin of
        # the ESI file), else hil's
        rx, tx = (content.rx_pdos, content.tx_pdos) if pdos_from_sii else \
            default_pdos(self.node)
        pdos, values = self.node.pdos.by_object, self.node.objects.values
        self.assignment = {RXPDO_ASSIGN: Assignment(RXPDO_ASSIGN, rx, pdos, values),
                           TXPDO_ASSIGN: Assignment(TXPDO_ASSIGN, tx, pdos, values)}
        self.esc = Esc(self, build_sii(content), last=last)
        self.coe = CoeServer(self._upload, self._download,
                             content.mailbox(SM_TYPE_MAILBOX_OUT).length)
        self.node.boot()

    def _free_mappings(self) -> None:
        """The PDO mappings changeable in PRE-OP: a CAN COB-ID means nothing on EtherCAT, so
        every PDO's is marked not valid (CiA 301 freezes a valid PDO's mapping)."""
        values = self.node.objects.values
        for pdo in self.node.pdos.pdos:
            if pdo.comm is not None:
                values[(pdo.comm, 1)] |= PDO_NOT_VALID
        self.node.pdos.compile_all()

    # -- what a CAN node would send --------------------------------------------------------
    def _from_drive(self, frames: list[Frame]) -> None:
        emcy_id = EMCY_BASE + self.node.node_id
        for can_id, data in frames:
            if can_id == emcy_id and len(data) >= 3:
                code, register = struct.unpack_from("<HB", data)
                self._messages.append(emergency(code, register, bytes(data[3:8])))

    def unsolicited(self) -> list[bytes]:
        messages, self._messages = self._messages, []
        return messages

    # -- the objects, as CoE serves them ----------------------------------------------------
    def _upload(self, index: int, subindex: int) -> bytes:
        if index == SM_COMM_TYPES:
            if subindex > len(SM_TYPES):
                raise SdoAbortError(ABORT_NO_SUBINDEX)
            return bytes([SM_TYPES[subindex - 1] if subindex else len(SM_TYPES)])
        if index in self.assignment:
            return self.assignment[index].read(subindex)
        return self.node.upload(index, subindex)

    def _download(self, index: int, subindex: int, data: bytes) -> None:
        if index == SM_COMM_TYPES:
            raise SdoAbortError(ABORT_READ_ONLY)
        mapping = index in RXPDO_MAPPINGS or index in TXPDO_MAPPINGS
        if (mapping or index in self.assignment) and self.esc.state != PRE_OP:
            raise SdoAbortError(ABORT_DEVICE_STATE)  # PDOs are set up in PRE-OP
        if index in self.assignment:
            self.assignment[index].write(subindex, int.from_bytes(data, "little"))
            return
        if self.esc.state == OP and any((index, subindex) in pdo.keys
                                        for pdo in self._pdos(RXPDO_ASSIGN)):
            # the outputs write it every cycle, before the drive's cycle reads it: a
            # controlword written so never reaches the state machine (the RxPDO's does)
            self.node.store(index, subindex, data)
            return
        self.node.download(index, subindex, data)

    # -- process data ------------------------------------------------------------------------
    def _pdos(self, index: int) -> list[Pdo]:
        by_object = self.node.pdos.by_object
        return [by_object[mapping] for mapping in self.assignment[index].assigned]

    @property
    def output_size(self) -> int:
        return sum(pdo.layout.size for pdo in self._pdos(RXPDO_ASSIGN))

    @property
    def input_size(self) -> int:
        return sum(pdo.layout.size for pdo in self._pdos(TXPDO_ASSIGN))

    def cycle(self, outputs: bytes | None) -> bytes:
        """One process-data cycle: the outputs (None in SAFE-OP: not applied) to the drive,
        one period on, the inputs as they are then."""
        received: list[tuple[Pdo, bytes]] = []
        if outputs is not None:
            at = 0
            for pdo in self._pdos(RXPDO_ASSIGN):
                received.append((pdo, outputs[at:at + pdo.layout.size]))
                at += pdo.layout.size
        self.node.process_data_cycle(received)
        return b"".join(self.node.pdo_data(pdo) for pdo in self._pdos(TXPDO_ASSIGN))

    # -- the ESC's other questions -------------------------------------------------------------
    def mailbox(self, request: bytes) -> list[bytes]:
        return self.coe.handle(request)

    def refuse(self, requested: int) -> int:
        """SAFE-OP needs every mandatory PDO assigned."""
        if requested != SAFE_OP:
            return 0
        return next((code for assignment in self.assignment.values()
                     if (code := assignment.refusal())), 0)

    def entered(self, state: int, left: int) -> None:
        if state == OP or left == OP:
            self.node.set_operational(state == OP)

    def service(self) -> None:
        """Between frames: the drive's timers, and its emergencies into the mailbox."""
        self.node.service()
        self.esc.poll()


def default_sii(node: DriveNode) -> SiiContent:
    """hil's SII for ``node``: its identity (0x1018), its name (0x1008), its default PDOs."""
    def u32(sub: int) -> int:
        return int.from_bytes(node.upload(IDENTITY, sub), "little")

    name = node.upload(DEVICE_NAME, 0).decode("ascii", "replace").rstrip("\0")
    rx, tx = default_pdos(node)
    return SiiContent(vendor_id=u32(1), product_code=u32(2), revision=u32(3), serial=u32(4),
                      name=name, rx_pdos=rx, tx_pdos=tx)


def default_pdos(node: DriveNode) -> tuple[tuple[PdoSpec, ...], tuple[PdoSpec, ...]]:
    """hil's default assignment (:data:`DEFAULT_ASSIGNMENT`) of ``node``'s PDOs, RxPDOs and
    TxPDOs, each as mapped now (a PDO mapping nothing left out)."""
    pdos = node.pdos.by_object

    def spec(mapping: int, sync_manager: int) -> PdoSpec:
        entries = []
        for index, subindex in pdos[mapping].keys:
            var = node.objects.find(index, subindex)
            entries.append(PdoEntrySpec(index, subindex, len(var), var.data_type or 0))
        return PdoSpec(mapping, sync_manager, tuple(entries))

    def specs(assign: int, sync_manager: int) -> tuple[PdoSpec, ...]:
        return tuple(spec(m, sync_manager) for m in DEFAULT_ASSIGNMENT[assign]
                     if m in pdos and pdos[m].keys)

    return specs(RXPDO_ASSIGN, 2), specs(TXPDO_ASSIGN, 3)
