"""One EtherCAT segment (a NIC, a veth end) through SOEM's master (pysoem): its slaves as
SOEM's scan finds them (``config_init``: station addresses, SII, mailbox), their AL states, the
process-data image (``config_map`` reads each slave's PDO assignment over CoE and programs the
SyncManagers and FMMUs; one LRW a cycle) and the working counter of every cycle.

Several axes share a segment: each master stages its slave's outputs; alone on it (or while
setting up) a master's stage sends the frame at once, cycling together (:meth:`cycle_together`)
the frame goes out at :meth:`end_cycle`, once for every axis. The first master to read a cycle
collects the answer (the working counter and every slave's inputs) for all.

pysoem holds the GIL in SOEM's waits unless asked: the cyclic receive and the mailbox waits let
it go, so the rest of hil (the session's writer thread) runs meanwhile. SOEM 1.4 takes a CoE
SDO abort only when the slave codes it as a request (as ETG.1000.6 has it); from a slave that
answers it as a response, a refused download passes for done and a refused upload is a
"packet error". So the CiA 402 master talks CoE itself over the mailbox registers
(:mod:`hil.drivers.ethercat.coe`), taking either, each wait bounded by its own clock.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

from hil.drivers.canopen.errors import DriveError, DriveLinkLostError, DriveNotFoundError
from hil.protocols.ethercat import (
    FEATURE_DC,
    INIT,
    OP,
    PRE_OP,
    REG_AL_STATUS,
    REG_FEATURES,
    SAFE_OP,
    SII_RX_MAILBOX,
    SII_TX_MAILBOX,
    al_state_text,
    al_status_text,
)

EXTRA = "the ethercat extra (pip install 'hil[ethercat]': pysoem, SOEM's Python binding)"
NO_FRAME = -1           # SOEM: no frame came back within the time-out
STATE_TIMEOUT_US = 2_000_000


#: SOEM's waits for a datagram's answer [us]: its defaults (2 ms, 20 ms for the scan's first)
#: assume a slave that answers in microseconds; a frame lost on a real NIC is rare, so longer
#: waits cost nothing there, and a slave in a busy process (hil's own, a loaded machine) is
#: not taken for absent. ``tx_mailbox`` too (20 ms): ``config_map`` reads each slave's PDO
#: assignment over CoE, and a read whose request found the mailbox busy that long fails, so
#: SOEM sizes the SyncManagers from the SII's PDOs instead, and the slave refuses SAFE-OP
SOEM_TIMEOUTS_US = {"ret": 50_000, "safe": 200_000, "eeprom": 200_000, "tx_mailbox": 200_000}
SCAN_TRIES = 3


def load_pysoem() -> Any:
    """pysoem (its waits set to :data:`SOEM_TIMEOUTS_US`), or a DriveError saying how to
    install it."""
    try:
        import pysoem
    except ImportError:
        raise DriveError(f"EtherCAT needs {EXTRA}") from None
    for name, us in SOEM_TIMEOUTS_US.items():
        setattr(pysoem.settings.timeouts, name, max(us, getattr(pysoem.settings.timeouts, name)))
    return pysoem


class Segment:
    """The slaves on ``iface``, found when it opens; ``name`` is how errors and events call it
    (``ethercat://IFACE``)."""

    def __init__(self, iface: str, name: str | None = None) -> None:
        self.iface = iface
        self.name = name or f"ethercat://{iface}"
        self.pysoem = load_pysoem()
        self.master = self.pysoem.Master()
        self.slaves: list[Any] = []
        self.mapped = False
        self.dc_slaves: list[int] = []  # the positions SYNC0 runs on
        self.in_op: set[int] = set()    # the positions this master put in OP: process data flows
        self.together = False
        self.cycles = 0          # process-data frames sent: lockstep's time, one period each
        self.wkc = NO_FRAME      # the last cycle's working counter
        self._answered = 0       # the cycle whose answer was collected
        self._users = 0
        self.open()

    # -- the slaves ---------------------------------------------------------------------------
    def open(self) -> None:
        """Open the interface and scan the line (SOEM's ``config_init``): every slave in
        PRE-OP, its station address and mailbox set."""
        try:
            self.master.open(self.iface)
        except ConnectionError:
            raise DriveLinkLostError(
                f"cannot open {self.name}: no interface {self.iface!r}, or no permission (a "
                "raw socket needs root or CAP_NET_RAW)") from None
        found = 0
        for _ in range(SCAN_TRIES):  # a line that answers nothing is scanned again
            found = self.master.config_init()
            if found > 0:
                break
        self.slaves = list(self.master.slaves) if found > 0 else []
        self.mapped = False
        self.in_op = set()
        self._mailboxes: dict[int, tuple[int, int, int, int]] = {}

    def reopen(self) -> None:
        """After a lost link: close, open and scan again."""
        self.master.close()
        self.open()

    def slave(self, position: int) -> Any:
        """pysoem's slave at ``position`` (1 = the first after the master)."""
        if not 1 <= position <= len(self.slaves):
            found = (f"{len(self.slaves)} slave{'s' if len(self.slaves) != 1 else ''} answered"
                     if self.slaves else "no slave answered a scan (is the line powered and "
                     "plugged into this interface?)")
            raise DriveNotFoundError(f"no EtherCAT slave {position} on {self.name}: {found} "
                                     "(the slave's position: ?slave=N in the URL)")
        return self.slaves[position - 1]

    def mailbox(self, position: int) -> tuple[int, int, int, int]:
        """The slave's mailbox from its SII: out start, size; in start, size."""
        if position not in self._mailboxes:
            slave = self.slave(position)
            out_start, out_size = struct.unpack("<HH", slave.eeprom_read(SII_RX_MAILBOX)[:4])
            in_start, in_size = struct.unpack("<HH", slave.eeprom_read(SII_TX_MAILBOX)[:4])
            if not out_size:
                raise DriveError(f"EtherCAT slave {position} on {self.name} has no mailbox: no "
                                 "CoE, so no CiA 402 drive hil can configure")
            self._mailboxes[position] = (out_start, out_size, in_start, in_size or out_size)
        return self._mailboxes[position]

    def al_status(self, position: int) -> tuple[int, int]:
        """The slave's AL status (state, error flag) and status code, read now."""
        status, _, code = struct.unpack("<HHH", self.fprd(position, REG_AL_STATUS, 6))
        return status, code

    def fprd(self, position: int, address: int, size: int, wait_us: int = 200_000) -> bytes:
        """``size`` bytes of the slave's memory at ``address`` (one FPRD, waited ``wait_us``
        for)."""
        try:
            data: bytes = self.slave(position)._fprd(address, size, wait_us)
        except self.pysoem.WkcError:
            raise DriveLinkLostError(f"EtherCAT slave {position} on {self.name} did not answer "
                                     f"a read of 0x{address:04X}") from None
        return data

    def fpwr(self, position: int, address: int, data: bytes) -> None:
        try:
            self.slave(position)._fpwr(address, data, 200_000)
        except self.pysoem.WkcError:
            raise DriveLinkLostError(f"EtherCAT slave {position} on {self.name} did not take "
                                     f"a write to 0x{address:04X}") from None

    # -- AL states ------------------------------------------------------------------------------
    def request(self, position: int, state: int, wait_us: int = STATE_TIMEOUT_US) -> None:
        """Ask one slave for AL ``state`` and wait for it; a refusal names the AL status code
        the slave gives."""
        slave = self.slave(position)
        slave.state = state
        slave.write_state()
        reached = slave.state_check(state, wait_us)
        if reached != state:
            status, code = self.al_status(position)
            raise DriveError(f"EtherCAT slave {position} on {self.name} stays in "
                             f"{al_state_text(status)} asked for {al_state_text(state)}: AL "
                             f"status code {al_status_text(code)}")

    def pre_operational(self, position: int) -> None:
        """Back to PRE-OP (the PDOs are set up there); the image is mapped again after."""
        self.in_op.discard(position)
        status, _ = self.al_status(position)
        if status & 0x0F in (INIT, PRE_OP) and not status & 0x10:
            if status & 0x0F == INIT:
                self.request(position, PRE_OP)
            return
        self.request(position, PRE_OP)
        self.mapped = False

    def operational(self, period_s: float) -> None:
        """The process-data image mapped (once every axis is configured), the distributed
        clocks set up where the slaves have them (SYNC0 every ``period_s``), then every slave
        to SAFE-OP and OP, process data flowing."""
        if not self.mapped:
            try:
                self.master.config_map()
            except self.pysoem.ConfigMapError as exc:
                raise DriveError(f"{self.name}: SOEM could not map the process data: "
                                 f"{exc}") from None
            self.mapped = True
            self.in_op = set()
            self._synchronize(period_s)
            for position in range(1, len(self.slaves) + 1):
                self.request(position, SAFE_OP)
        for position in range(1, len(self.slaves) + 1):
            status, _ = self.al_status(position)
            if status & 0x0F != OP:
                self.exchange()  # outputs valid before OP, as a slave expects
                self.request(position, OP)
            self.in_op.add(position)

    def _synchronize(self, period_s: float) -> None:
        """Distributed clocks (SOEM's ``config_dc``: the slaves' clocks measured and aligned on
        the first DC slave's; each frame then carries its system time): SYNC0 every cycle on
        each slave that has them (ESC features, 0x0008)."""
        self.dc_slaves = []
        if not self.master.config_dc():
            return
        for position, slave in enumerate(self.slaves, start=1):
            (features,) = struct.unpack("<H", self.fprd(position, REG_FEATURES, 2))
            if features & FEATURE_DC:
                slave.dc_sync(True, round(period_s * 1e9))
                self.dc_slaves.append(position)

    # -- process data ---------------------------------------------------------------------------
    def cycle_together(self, on: bool = True) -> None:
        """Hold every axis' outputs for :meth:`end_cycle` (on), or send each as it comes."""
        self.together = on

    def stage(self, position: int, outputs: bytes) -> None:
        """The slave's outputs for the next frame; sent at once unless cycling together."""
        self.slave(position).output = outputs
        if not self.together:
            self.send()

    def end_cycle(self) -> None:
        if self.together:
            self.send()

    def send(self) -> None:
        """One process-data frame (LRW) with every slave's outputs."""
        if not self.mapped:
            self.cycles += 1  # time passes in lockstep, no frame to send before the mapping
            self._answered = self.cycles
            self.wkc = NO_FRAME
            return
        self._collect(0)  # the last frame's answer first, should nobody have read it
        self.master.send_processdata()
        self.cycles += 1

    def collect(self, timeout_s: float) -> int:
        """The working counter of the last frame, waiting at most ``timeout_s`` for it (the
        first reader waits; the others get the same answer)."""
        return self._collect(round(timeout_s * 1e6))

    def _collect(self, timeout_us: int) -> int:
        if self._answered != self.cycles:
            self._answered = self.cycles
            self.wkc = self.master.receive_processdata(max(timeout_us, 1), release_gil=True)
        return self.wkc

    def exchange(self, timeout_s: float = 0.1) -> int:
        """One frame out and its answer in (commissioning, and letting lockstep time pass)."""
        self.send()
        return self.collect(timeout_s)

    def inputs(self, position: int) -> bytes:
        data: bytes = self.slave(position).input
        return data

    @property
    def expected_wkc(self) -> int:
        return int(self.master.expected_wkc)

    # -- users ----------------------------------------------------------------------------------
    def use(self) -> Callable[[], None]:
        """One more master on the segment; the returned call releases it (the last one closes
        the segment: every slave back to INIT)."""
        self._users += 1
        released = False

        def release() -> None:
            nonlocal released
            if released:
                return
            released = True
            self._users -= 1
            if self._users == 0:
                self.close()
        return release

    def close(self) -> None:
        self.in_op = set()
        try:
            if self.slaves:
                self.master.state = INIT
                self.master.write_state()
        finally:
            self.master.close()
