"""CiA 402 state control: reach the drive, wait for a state, the controlwords to OPERATION
ENABLED, a fault reset (rising edge of bit 7). The tables are :mod:`hil.protocols.cia402`'s;
the two words travel on a :class:`StateWords` channel: by SDO (:class:`SdoWords`: 0x6040
written, 0x6041 read) on CAN, in the process data cycle by cycle on EtherCAT once the slave is
in OP (:mod:`hil.drivers.ethercat.words`), where its RxPDO would overwrite an SDO write."""

from __future__ import annotations

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
REACH_TIMEOUT_S = 0.2          # a first read this long unanswered: try NMT pre-operational
SDO_POLL_S = 0.002             # a wait for a state reads 0x6041 by SDO this often


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


class StateWords(Protocol):
    """Where a master's controlword goes and the drive's statusword comes from."""

    def controlword(self, word: int) -> None:
        """Send ``word`` (the drive takes it before the next :meth:`statusword`)."""

    def statusword(self, timeout_s: float | None = None) -> int:
        """The drive's statusword now (its answer waited for at most ``timeout_s`` where
        given); a DriveLinkLostError when none comes."""

    def pause(self) -> None:
        """Let the drive's time pass between two reads of a wait."""


class SdoWords:
    """The two words by SDO: 0x6040 written, 0x6041 read, a read every :data:`SDO_POLL_S` of
    a wait."""

    def __init__(self, sdo: SdoChannel, clock: MasterClock) -> None:
        self.sdo, self.clock = sdo, clock

    def controlword(self, word: int) -> None:
        self.sdo.write(CONTROLWORD, 0, word, "<H")

    def statusword(self, timeout_s: float | None = None) -> int:
        return self.sdo.read_int(STATUSWORD, 0, "<H", timeout_s)

    def pause(self) -> None:
        self.clock.sleep(SDO_POLL_S)


class StateControl:
    """The CiA 402 state machine of drive ``node_id``, its two words on ``words``."""

    def __init__(self, words: StateWords, nmt: NmtCommands, clock: MasterClock,
                 state_timeout_s: float, sdo_timeout_s: float, node_id: int) -> None:
        self.words, self.nmt, self.clock = words, nmt, clock
        self.state_timeout_s, self.sdo_timeout_s = state_timeout_s, sdo_timeout_s
        self.node_id = node_id

    def statusword(self) -> int:
        return self.words.statusword()

    def controlword(self, word: int) -> None:
        self.words.controlword(word)

    def reach(self) -> int:
        """The statusword; a node that does not answer (in NMT STOPPED: no SDO) is sent to
        PRE-OPERATIONAL, and asked again.

        NMT is not sent first on purpose: a drive left enabled in OPERATIONAL may take leaving
        OPERATIONAL as a communication fault."""
        try:
            return self.words.statusword(min(REACH_TIMEOUT_S, self.sdo_timeout_s))
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
            self.words.pause()

    def enable(self) -> None:
        """SWITCH ON DISABLED awaited (a drive may still be in NOT READY TO SWITCH ON, whose
        way out is its own), then the controlwords to OPERATION ENABLED, each state awaited."""
        self.wait_state(SWITCH_ON_DISABLED, "the drive's own transition 1")
        for word, wanted in ENABLE_STEPS:
            self.controlword(word)
            self.wait_state(wanted, f"controlword 0x{word:04X}")

    def fault_reset(self) -> None:
        """FAULT -> SWITCH ON DISABLED: disable voltage, then the rising edge of bit 7."""
        self.controlword(CW_DISABLE_VOLTAGE)
        self.controlword(CW_FAULT_RESET)
        self.wait_state(SWITCH_ON_DISABLED, "fault reset")
        self.controlword(CW_DISABLE_VOLTAGE)
