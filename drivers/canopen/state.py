"""CiA 402 state control by SDO: reach the drive, wait for a state, the controlwords to
OPERATION ENABLED, a fault reset (rising edge of bit 7), and the safe stop (quick stop on the
cyclic channel until standstill or its time-out, then disable voltage). The tables are
:mod:`hil.protocols.cia402`'s."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from hil.drivers.canopen.errors import DriveLinkLostError, DriveStateError
from hil.drivers.canopen.sdo import SdoChannel
from hil.protocols.cia301 import NMT_ENTER_PRE_OPERATIONAL
from hil.protocols.cia402 import (
    CONTROLWORD,
    CW_DISABLE_VOLTAGE,
    CW_FAULT_RESET,
    STATUSWORD,
    SWITCH_ON_DISABLED,
    enable_steps,
    state_of,
)

ENABLE_STEPS = enable_steps()  # (controlword, state it leads to) from SWITCH ON DISABLED
REACH_TIMEOUT_S = 0.2          # a first SDO read this long unanswered: try NMT pre-operational


class MasterClock(Protocol):
    """The time a master goes by: ``time_ns`` for its heartbeats and watchdogs, ``sleep`` to
    let the drive's time pass while it waits for a state (in lockstep the rig makes that time
    pass for the emulated drive)."""

    def time_ns(self) -> int: ...

    def sleep(self, seconds: float) -> None: ...


class NmtCommands(Protocol):
    """The drive's communication state by command (CiA 301 NMT on CAN; the AL state on
    EtherCAT, where ``NMT_START`` is OP)."""

    def command(self, command: int) -> None: ...


class StateControl:
    """The CiA 402 state machine of one drive, driven by SDO."""

    def __init__(self, sdo: SdoChannel, nmt: NmtCommands, clock: MasterClock,
                 state_timeout_s: float, sdo_timeout_s: float) -> None:
        self.sdo, self.nmt, self.clock = sdo, nmt, clock
        self.state_timeout_s, self.sdo_timeout_s = state_timeout_s, sdo_timeout_s
        self.node_id = sdo.node_id

    def statusword(self) -> int:
        return self.sdo.read_int(STATUSWORD, 0, "<H")

    def controlword(self, word: int) -> None:
        self.sdo.write(CONTROLWORD, 0, word, "<H")

    def reach(self) -> int:
        """The statusword by SDO; a node in NMT STOPPED (no SDO) is sent to PRE-OPERATIONAL.

        NMT is not sent first on purpose: a drive left enabled in OPERATIONAL may take leaving
        OPERATIONAL as a communication fault."""
        try:
            return self.sdo.read_int(STATUSWORD, 0, "<H",
                                     min(REACH_TIMEOUT_S, self.sdo_timeout_s))
        except DriveLinkLostError:
            self.nmt.command(NMT_ENTER_PRE_OPERATIONAL)
        return self.statusword()

    def wait_state(self, wanted: str, why: str, timeout_s: float | None = None) -> int:
        """Poll the statusword until the drive is in ``wanted`` (DriveStateError after
        ``timeout_s``, by default the state time-out, naming where it is stuck)."""
        start = self.clock.time_ns()
        deadline_s = self.state_timeout_s if timeout_s is None else timeout_s
        while True:
            statusword = self.statusword()
            if state_of(statusword) == wanted:
                return statusword
            if (self.clock.time_ns() - start) / 1e9 > deadline_s:
                raise DriveStateError(
                    f"drive node {self.node_id} stuck in {state_of(statusword)} (statusword "
                    f"0x{statusword:04X}) waiting for {wanted} ({why}) after "
                    f"{deadline_s:g} s")
            self.clock.sleep(0.002)

    def enable(self, on_step: Callable[[], None] | None = None) -> None:
        """The controlwords from SWITCH ON DISABLED to OPERATION ENABLED, each state awaited."""
        for word, wanted in ENABLE_STEPS:
            self.controlword(word)
            self.wait_state(wanted, f"controlword 0x{word:04X}")

    def fault_reset(self) -> None:
        """FAULT -> SWITCH ON DISABLED: disable voltage, then the rising edge of bit 7."""
        self.controlword(CW_DISABLE_VOLTAGE)
        self.controlword(CW_FAULT_RESET)
        self.wait_state(SWITCH_ON_DISABLED, "fault reset")
        self.controlword(CW_DISABLE_VOLTAGE)
