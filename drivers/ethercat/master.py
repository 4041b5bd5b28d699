"""The CiA 402 master of one drive on EtherCAT (CoE): the CAN master's mode table, state
machine, settings journal, limits, stops and events (:class:`CanDriveMaster`, whose transport
hooks this fills), over an EtherCAT segment instead of a CAN bus.

What is EtherCAT's own:

* the SDO is CoE in the slave's mailbox (:class:`~hil.drivers.ethercat.coe.CoeSdo`), its
  emergencies the CAN EMCY's eight bytes, so they become the same ``drive.emcy`` events;
* NMT is the AL state: pre-operational is PRE-OP, start is SAFE-OP then OP (the process-data
  image mapped first, once every axis of the segment is configured);
* :meth:`configure` maps the mode's RxPDO and the TxPDOs into 0x1600 / 0x1A00.. and assigns them
  to the SyncManagers (0x1C12 / 0x1C13), in PRE-OP; no heartbeats (the working counter of every
  cycle tells whether the slave is there);
* the state machine's two words (:mod:`~hil.drivers.ethercat.words`): in OP the
  controlwords of the enabling, a fault reset and an open go out in the RxPDO of a cycle and
  the statusword is the TxPDO's, cycle by cycle (a drive's RxPDO overwrites an SDO write of
  0x6040); by SDO only where no process data flows (PRE-OP, a segment scanned again after a
  lost link);
* the cyclic exchange is one LRW a cycle (:mod:`~hil.drivers.ethercat.cyclic`); its working
  counter is checked every cycle; the mailbox is looked into every
  :data:`MAILBOX_POLL_CYCLES` cycles and whenever the drive reports a fault (its emergency);
* distributed clocks where the slaves have them: their clocks aligned, SYNC0 every cycle;
* in lockstep the master's time is its process-data cycles (the link's ``syncs_sent``), which
  are the time of hil's emulated slave too.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

from hil.contracts import EventSink, no_event
from hil.drivers.can_bus_time import BusBudget
from hil.drivers.canopen.config import DriveMasterConfig
from hil.drivers.canopen.cyclic import CyclicExchange, Feedback
from hil.drivers.canopen.errors import DriveLinkLostError
from hil.drivers.canopen.link import Link
from hil.drivers.canopen.master import CanDriveMaster
from hil.drivers.canopen.sdo import SdoChannel
from hil.drivers.canopen.state import MasterClock, NmtCommands, SdoWords, StateWords
from hil.drivers.ethercat.coe import CoeSdo
from hil.drivers.ethercat.cyclic import ProcessDataExchange
from hil.drivers.ethercat.segment import Segment
from hil.drivers.ethercat.words import ProcessDataWords, SegmentWords
from hil.protocols.can_frames import Frame
from hil.protocols.cia301 import CYCLE_PERIOD, NMT_ENTER_PRE_OPERATIONAL, NMT_START, SYNC_COB_ID
from hil.protocols.cia402 import FAULT, FAULT_REACTION_ACTIVE, PdoMap
from hil.protocols.ethercat import RXPDO_ASSIGN, TXPDO_ASSIGN

# a look for emergencies every this many cycles (100 ms at 2 kHz): a read of the slave's
# mailbox is a round trip of its own in the loop's read phase
MAILBOX_POLL_CYCLES = 200
ETHERNET_OVERHEAD_BYTES = 14 + 4 + 8 + 12 + 2 + 12 + 2  # header, FCS, preamble, gap; ECAT, LRW
FAST_ETHERNET = 100_000_000


class SegmentLink:
    """The :class:`~hil.drivers.canopen.link.Link` an EtherCAT master gives the CAN master's
    parts: no CAN frame travels; a SYNC (a lockstep clock letting time pass) is one
    process-data cycle of the segment, and the segment's cycles are the lockstep time."""

    watched_ids: frozenset[int] = frozenset()

    def __init__(self, segment: Segment, position: int) -> None:
        self.segment, self.position = segment, position

    @property
    def name(self) -> str:
        return f"{self.segment.name}?slave={self.position}"

    @property
    def syncs_sent(self) -> int:
        return self.segment.cycles

    def send(self, frames: list[Frame]) -> None:
        if any(can_id == SYNC_COB_ID for can_id, _ in frames):
            self.segment.exchange()

    def recv(self, timeout: float | None) -> Frame | None:
        return None

    def own_echo(self, frame: Frame) -> bool:
        return False

    def reconnect(self) -> None:
        self.segment.reopen()

    def shutdown(self) -> None:
        """The segment is released by the master's closers (the last one closes it)."""


class AlStates:
    """NMT commands as AL states: pre-operational is PRE-OP, start is OP."""

    def __init__(self, segment: Segment, position: int, period_s: float) -> None:
        self.segment, self.position, self.period_s = segment, position, period_s

    def command(self, command: int) -> None:
        if command == NMT_ENTER_PRE_OPERATIONAL:
            self.segment.pre_operational(self.position)
        elif command == NMT_START:
            self.segment.operational(self.period_s)


def ethercat_budget(rpdo: PdoMap, tpdos: tuple[PdoMap, ...], period_s: float,
                    slaves: int = 1) -> BusBudget:
    """The wire time of one cycle's frame at 100 Mbit/s (every slave's process data in one
    LRW, at least a minimal Ethernet frame)."""
    data = slaves * (rpdo.size_bytes + sum(pdo.size_bytes for pdo in tpdos))
    bits = 8 * (ETHERNET_OVERHEAD_BYTES + max(data, 46 - 12 - 2 - 2))
    wire_us = bits / FAST_ETHERNET * 1e6
    return BusBudget(FAST_ETHERNET, period_s * 1e6, wire_us, wire_us, ())


class EthercatDriveMaster(CanDriveMaster):
    """CiA 402 master for the drive at ``position`` (1 = the first slave) on ``segment``;
    ``config.node_id`` names it in events and errors, as on CAN."""

    def __init__(self, segment: Segment, position: int,
                 config: DriveMasterConfig | None = None, *, on_event: EventSink = no_event,
                 clock: MasterClock | None = None, closers: tuple[Callable[[], None], ...] = (),
                 url: str | None = None) -> None:
        self.segment, self.position = segment, position
        segment.slave(position)  # a position with no slave is said now
        super().__init__(SegmentLink(segment, position), config, on_event=on_event,
                         clock=clock, closers=closers, url=url)
        self.heartbeat_watch.period_ms = 0  # no heartbeat: the working counter says it
        self.budget = ethercat_budget(self.operation.rpdo1(), self._tpdo_maps,
                                      self.config.cycle_period_s)
        self._since_poll = 0

    # -- the transport's services -----------------------------------------------------------
    def _new_sdo(self, link: Link) -> SdoChannel:
        c = self.config
        self.coe = CoeSdo(self.segment, self.position, c.node_id,
                          max(c.sdo_timeout_s, c.lockstep_timeout_s if c.lockstep else 0.0),
                          self._on_emcy)
        return self.coe

    def _new_nmt(self, link: Link) -> NmtCommands:
        return AlStates(self.segment, self.position, self.config.cycle_period_s)

    def _new_cyclic(self, link: Link) -> CyclicExchange:
        c = self.config
        self.process_data = ProcessDataExchange(
            self.segment, self.position, link, c.node_id, self.operation.rpdo1(),
            self._tpdo_maps, rx_timeout_s=c.rx_timeout_s,
            period_s=c.cycle_period_s, watchdog=self.watchdog, silence_is_gone=c.lockstep,
            now_ns=self._clock.time_ns, before_cycle=self.coe.flush,
            after_cycle=self._look_in_mailbox)
        return self.process_data

    def _new_words(self) -> StateWords:
        """In the process data while the slave is in OP, by SDO while it is not."""
        in_cycles = ProcessDataWords(self.process_data, self._holding_target, self._clock,
                                     self.config.cycle_period_s)
        return SegmentWords(self.segment, self.position, in_cycles,
                            SdoWords(self.sdo, self._clock))

    def _enabled_feedback(self) -> None:
        """The last cycle's answer: the enabling's last statusword came in it."""
        return None

    def _look_in_mailbox(self, feedback: Feedback) -> None:
        """The slave's emergencies: every few cycles, and at once when it reports a fault."""
        self._since_poll += 1
        faulted = feedback.state in (FAULT, FAULT_REACTION_ACTIVE)
        if faulted or self._since_poll >= MAILBOX_POLL_CYCLES:
            self._since_poll = 0
            # a read not answered within a cycle's wait is left: the next working counter
            # tells whether the slave is there
            with contextlib.suppress(DriveLinkLostError):
                self.coe.poll(self.config.rx_timeout_s)

    # -- configuration ----------------------------------------------------------------------------
    def _configure_transport(self) -> None:
        """PRE-OP; the mode's RxPDO and the TxPDOs mapped and assigned to the SyncManagers
        (sub-index 0 cleared first, then the entries, then the count: ETG.1020's order); the
        cycle period where the drive has 0x1006 (hil's emulated drive steps its axis by it)."""
        sdo = self.sdo
        self.nmt.command(NMT_ENTER_PRE_OPERATIONAL)
        rpdo = self.operation.rpdo1()
        for assign, pdos in ((RXPDO_ASSIGN, (rpdo,)), (TXPDO_ASSIGN, self._tpdo_maps)):
            sdo.write(assign, 0, 0, "<B")
            for pdo in pdos:
                entries = pdo.mapping_values()
                sdo.write(pdo.mapping, 0, 0, "<B")
                for sub, entry in enumerate(entries, start=1):
                    sdo.write(pdo.mapping, sub, entry)
                sdo.write(pdo.mapping, 0, len(entries), "<B")
            for sub, pdo in enumerate(pdos, start=1):
                sdo.write(assign, sub, pdo.mapping, "<H")
            sdo.write(assign, 0, len(pdos), "<B")
        self._write_where_present(CYCLE_PERIOD, 0, round(self.config.cycle_period_s * 1e6))

    def use_mode(self, name: str) -> None:
        """As on CAN; the process-data image is mapped again (PRE-OP first) at the next
        :meth:`configure`."""
        super().use_mode(name)
        self.segment.mapped = False

    def _enable_operation(self) -> None:
        """The segment is in OP (the NMT start before this): said once, then the enabling,
        through the process data."""
        segment, n = self.segment, self.node_id
        sync0_ns = round(self.config.cycle_period_s * 1e9) \
            if self.position in segment.dc_slaves else None
        clock = f"SYNC0 every {sync0_ns / 1e3:g} us" if sync0_ns else "no distributed clock"
        self._event("ethercat.operational", f"drive node {n}: EtherCAT slave {self.position} "
                    f"on {segment.name} in OP, working counter {segment.expected_wkc} a "
                    f"cycle, {clock}", slave=self.position, expected_wkc=segment.expected_wkc,
                    sync0_ns=sync0_ns)
        self._confirm_mode_in_op()
        super()._enable_operation()

    def _confirm_mode(self) -> None:
        """Not in PRE-OP: a drive may apply 0x6060 only once it runs its cycles (SAFE-OP,
        OP); :meth:`_confirm_mode_in_op` checks it there."""

    def _confirm_mode_in_op(self) -> None:
        """In OP, before the enabling: cycles until the drive shows the mode written (0x6061
        read by CoE after each), for up to the state time-out; else a DriveStateError."""
        deadline_ns = self._clock.time_ns() + round(self.config.state_timeout_s * 1e9)
        while self._mode_shown() != self.operation.code and self._clock.time_ns() < deadline_ns:
            self.states.statusword()  # a cycle: the drive takes its outputs
        super()._confirm_mode()

    def describe(self) -> dict[str, Any]:
        described = super().describe()
        described["ethercat"] = {"interface": self.segment.iface, "slave": self.position,
                                 "name": self.segment.slave(self.position).name}
        return described
