"""The EtherCAT slave controller (ESC) as a master sees it: 64 KiB of registers and process
memory that datagrams read and write, and what some writes mean.

* addressing: auto-increment (position), configured station address, broadcast, and logical
  through the FMMUs (byte-granular); the working counter each datagram earns (read 1, write 1,
  read-write 3; logical: 1 for the reading FMMUs, 2 for the writing ones);
* the AL state machine (0x0120 control, 0x0130 status, 0x0134 status code): INIT, PRE-OP,
  SAFE-OP, OP one step up at a time, any step down; a transition the configuration does not
  allow is refused with the error flag and ETG.1000's status code (mailbox SyncManagers not as
  the SII says: 0x0016; process-data SyncManagers not the PDOs' sizes: 0x001D / 0x001E), and
  an error holds the state until the master acknowledges it;
* the SII EEPROM interface (0x0502..0x050F: read commands answered at once, 8 bytes a read);
* the SyncManagers: SM0 a mailbox written by the master (handed to the application when its
  last byte is written), SM1 the mailbox the master reads (the next answer put in when the last
  byte was read; status bit 3 full), SM2/SM3 the process data;
* minimal distributed-clock registers: the receive times latched by a write to 0x0900, the
  system time (0x0910: local time + offset 0x0920), SYNC0's activation and cycle kept.

The application behind it (:class:`EscApplication`, :mod:`hil.emulators.ethercat.slave`)
answers the mailbox, checks and takes the AL transitions, and runs one process-data cycle when
the outputs' last byte is written: inside the frame, between its writes and its reads, so the
inputs the frame carries back are those after the cycle (as a SYNC's TPDOs on CAN).
"""

from __future__ import annotations

import struct
import time
from collections import deque
from typing import Protocol

from hil.protocols.ethercat import (
    AL_ACK,
    AL_BOOTSTRAP_UNSUPPORTED,
    AL_ERROR,
    AL_INVALID_INPUT_CONFIG,
    AL_INVALID_MAILBOX_CONFIG,
    AL_INVALID_OUTPUT_CONFIG,
    AL_INVALID_STATE_CHANGE,
    AL_UNKNOWN_STATE,
    ARMW,
    AUTO_INCREMENT,
    BOOT,
    BRD,
    BROADCAST,
    CONFIGURED,
    EEPROM_COMMAND_MASK,
    EEPROM_ERROR_COMMAND,
    EEPROM_READ,
    EEPROM_READ_8_BYTES,
    FEATURE_DC,
    FEATURE_DC64,
    FMMU,
    FMMU_READ,
    FMMU_SIZE,
    FMMU_WRITE,
    FRMW,
    INIT,
    LOGICAL,
    LRD,
    LRW,
    LWR,
    OP,
    PRE_OP,
    READ_WRITES,
    READS,
    REG_AL_CONTROL,
    REG_AL_STATUS,
    REG_AL_STATUS_CODE,
    REG_DC_RECEIVE_TIME_UNIT,
    REG_DC_RECEIVE_TIMES,
    REG_DC_SYSTEM_OFFSET,
    REG_DC_SYSTEM_TIME,
    REG_DL_STATUS,
    REG_EEPROM_ADDRESS,
    REG_EEPROM_CONTROL,
    REG_EEPROM_DATA,
    REG_FEATURES,
    REG_FMMU0,
    REG_FMMUS,
    REG_PDI_CONTROL,
    REG_PORTS,
    REG_RAM_SIZE,
    REG_REVISION,
    REG_SM0,
    REG_STATION_ADDRESS,
    REG_SYNC_MANAGERS,
    REG_TYPE,
    SAFE_OP,
    SM_ACTIVATE_ENABLE,
    SM_SIZE,
    SM_STATUS_MAILBOX_FULL,
    SYNC_MANAGER,
    WRITES,
)

MEMORY = 0x10000
FMMU_COUNT, SM_COUNT = 8, 8
ESC_TYPE, ESC_REVISION = 0x11, 0x01   # reported as an ET1100
MAILBOX_OUT, MAILBOX_IN, OUTPUTS, INPUTS = 0, 1, 2, 3   # the SyncManagers' uses, by number
# registers the master cannot write: identity, DL status, AL status and code
READ_ONLY = ((REG_TYPE, 0x0010), (REG_DL_STATUS, REG_DL_STATUS + 2),
             (REG_AL_STATUS, REG_AL_STATUS_CODE + 2))
DL_PORT0 = 0x0001 | 0x0010 | 0x0200        # PDI up, link and communication on port 0
DL_PORT1_OPEN, DL_PORT1_CLOSED = 0x0020 | 0x0800, 0x0400
DL_PORTS_2_3_CLOSED = 0x1000 | 0x4000
STATE_ORDER = {INIT: 0, PRE_OP: 1, SAFE_OP: 2, OP: 3}


class EscApplication(Protocol):
    """What sits behind the ESC (the drive)."""

    @property
    def output_size(self) -> int: ...

    @property
    def input_size(self) -> int: ...

    def mailbox(self, request: bytes) -> list[bytes]: ...

    def unsolicited(self) -> list[bytes]: ...

    def refuse(self, requested: int) -> int: ...

    def entered(self, state: int, left: int) -> None: ...

    def cycle(self, outputs: bytes | None) -> bytes: ...


def _overlaps(start: int, end: int, register: int, size: int = 1) -> bool:
    return start < register + size and register < end


class Esc:
    """One slave's ESC over ``app``; ``sii``: its EEPROM image; ``last``: the end of the
    line (port 1 closed), which a master reads from the DL status."""

    def __init__(self, app: EscApplication, sii: bytes, *, last: bool = True) -> None:
        self.app = app
        self.sii = sii
        self.memory = bytearray(MEMORY)
        self._mailbox_out: deque[bytes] = deque()
        self._t0_ns = time.monotonic_ns()
        self.cycles = 0
        self.frames = 0
        self._init_registers(last)

    # -- registers ---------------------------------------------------------------------------
    def _init_registers(self, last: bool) -> None:
        mem = self.memory
        mem[REG_TYPE], mem[REG_REVISION] = ESC_TYPE, ESC_REVISION
        mem[REG_FMMUS], mem[REG_SYNC_MANAGERS], mem[REG_RAM_SIZE] = FMMU_COUNT, SM_COUNT, 8
        mem[REG_PORTS] = 0x0F
        struct.pack_into("<H", mem, REG_FEATURES, FEATURE_DC | FEATURE_DC64)
        struct.pack_into("<H", mem, REG_DL_STATUS, DL_PORT0 | DL_PORTS_2_3_CLOSED
                         | (DL_PORT1_CLOSED if last else DL_PORT1_OPEN))
        struct.pack_into("<H", mem, REG_PDI_CONTROL, struct.unpack_from("<H", self.sii)[0])
        struct.pack_into("<H", mem, REG_EEPROM_CONTROL, EEPROM_READ_8_BYTES)
        self._set_al(INIT, 0)

    def u16(self, address: int) -> int:
        value: int = struct.unpack_from("<H", self.memory, address)[0]
        return value

    @property
    def station_address(self) -> int:
        return self.u16(REG_STATION_ADDRESS)

    @property
    def al_status(self) -> int:
        return self.u16(REG_AL_STATUS)

    @property
    def state(self) -> int:
        return self.al_status & 0x0F

    def _set_al(self, status: int, code: int) -> None:
        struct.pack_into("<HxxH", self.memory, REG_AL_STATUS, status, code)

    def sync_manager(self, number: int) -> tuple[int, int, int, int, int]:
        """SM ``number``'s start, length, control, status, activate."""
        start, length, control, status, activate, _ = SYNC_MANAGER.unpack_from(
            self.memory, REG_SM0 + number * SM_SIZE)
        return start, length, control, status, activate

    def _sm_area(self, number: int) -> tuple[int, int] | None:
        start, length, _, _, activate = self.sync_manager(number)
        if not activate & SM_ACTIVATE_ENABLE or not length:
            return None
        return start, start + length

    def _set_sm_status(self, number: int, full: bool) -> None:
        address = REG_SM0 + number * SM_SIZE + 5
        if full:
            self.memory[address] |= SM_STATUS_MAILBOX_FULL
        else:
            self.memory[address] &= ~SM_STATUS_MAILBOX_FULL & 0xFF

    def local_time_ns(self) -> int:
        return time.monotonic_ns() - self._t0_ns

    # -- datagrams ---------------------------------------------------------------------------
    def datagram(self, command: int, adp: int, ado: int, data: memoryview) -> int:
        """Serve one datagram as it passes (``data`` changed in place); the working counter it
        adds. ``adp`` as it arrives here (auto-increment: 0 addresses this slave)."""
        if command in LOGICAL:
            return self._logical(command, adp | ado << 16, data)
        if command in AUTO_INCREMENT:
            addressed = adp == 0
        elif command in CONFIGURED:
            addressed = adp == self.station_address
        elif command in BROADCAST:
            addressed = True
        else:
            return 0
        if command in (ARMW, FRMW):  # the addressed slave reads, the others write
            if addressed:
                data[:] = self._read(ado, len(data))
            else:
                self._write(ado, bytes(data))
            return 1
        if not addressed:
            return 0
        if command in READS:
            read = self._read(ado, len(data))
            if command == BRD:  # every slave's value ORed into the datagram
                data[:] = bytes(a | b for a, b in zip(data, read, strict=True))
            else:
                data[:] = read
            return 1
        if command in WRITES:
            self._write(ado, bytes(data))
            return 1
        if command in READ_WRITES:
            read = self._read(ado, len(data))
            self._write(ado, bytes(data))
            data[:] = read
            return 3
        return 0

    def _logical(self, command: int, address: int, data: memoryview) -> int:
        end = address + len(data)
        reads: list[tuple[int, int, int]] = []
        wrote = read = False
        for number in range(FMMU_COUNT):
            (log_start, log_length, _, _, physical, _, kind,
             active) = FMMU.unpack_from(self.memory, REG_FMMU0 + number * FMMU_SIZE)
            if not active & 1 or not log_length:
                continue
            start, stop = max(address, log_start), min(end, log_start + log_length)
            if start >= stop:
                continue
            at = physical + start - log_start
            if kind & FMMU_WRITE and command in (LWR, LRW):
                self._write(at, bytes(data[start - address:stop - address]))
                wrote = True
            if kind & FMMU_READ and command in (LRD, LRW):
                reads.append((start - address, stop - address, at))
                read = True
        for offset, stop, at in reads:  # after the writes, and the cycle they completed
            data[offset:stop] = self._read(at, stop - offset)
        return (1 if read else 0) + (2 if wrote and command == LRW else 1 if wrote else 0)

    # -- memory with meaning ---------------------------------------------------------------
    def _read(self, address: int, size: int) -> bytes:
        end = address + size
        if _overlaps(address, end, REG_DC_SYSTEM_TIME, 8):
            offset = struct.unpack_from("<q", self.memory, REG_DC_SYSTEM_OFFSET)[0]
            struct.pack_into("<Q", self.memory, REG_DC_SYSTEM_TIME,
                             (self.local_time_ns() + offset) & 0xFFFF_FFFF_FFFF_FFFF)
        out = bytes(self.memory[address:end])
        mailbox = self._sm_area(MAILBOX_IN)
        if mailbox is not None and address < mailbox[1] <= end:  # the answer read: the next
            self._set_sm_status(MAILBOX_IN, False)
            self._load_mailbox()
        return out

    def _write(self, address: int, data: bytes) -> None:
        end = address + len(data)
        saved = [(lo, bytes(self.memory[lo:hi])) for lo, hi in READ_ONLY
                 if _overlaps(address, end, lo, hi - lo)]
        self.memory[address:end] = data
        for lo, kept in saved:
            self.memory[lo:lo + len(kept)] = kept
        if _overlaps(address, end, REG_AL_CONTROL, 2):
            self._al_control(self.u16(REG_AL_CONTROL))
        if _overlaps(address, end, REG_EEPROM_CONTROL, 2):
            self._eeprom_command()
        if _overlaps(address, end, REG_DC_RECEIVE_TIMES, 4):
            now = self.local_time_ns()
            struct.pack_into("<IIII", self.memory, REG_DC_RECEIVE_TIMES,
                             *((now + port * 100) & 0xFFFF_FFFF for port in range(4)))
            struct.pack_into("<Q", self.memory, REG_DC_RECEIVE_TIME_UNIT, now)
        mailbox = self._sm_area(MAILBOX_OUT)
        if mailbox is not None and address < mailbox[1] <= end and self.state != INIT:
            self._mailbox_request(bytes(self.memory[mailbox[0]:mailbox[1]]))
        outputs = self._sm_area(OUTPUTS)
        if outputs is not None and address < outputs[1] <= end and \
                self.state in (SAFE_OP, OP):
            self._cycle(bytes(self.memory[outputs[0]:outputs[1]]))

    # -- the mailbox ---------------------------------------------------------------------------
    def _mailbox_request(self, request: bytes) -> None:
        self._mailbox_out.extend(self.app.mailbox(request))
        self._load_mailbox()

    def _load_mailbox(self) -> None:
        """The next answer (or a message of the slave's own: an emergency) into SM1, when the
        master has read the last one."""
        area = self._sm_area(MAILBOX_IN)
        if area is None or self.memory[REG_SM0 + MAILBOX_IN * SM_SIZE + 5] & \
                SM_STATUS_MAILBOX_FULL:
            return
        self._mailbox_out.extend(self.app.unsolicited())
        if not self._mailbox_out:
            return
        message = self._mailbox_out.popleft()[:area[1] - area[0]]
        self.memory[area[0]:area[1]] = message.ljust(area[1] - area[0], b"\0")
        self._set_sm_status(MAILBOX_IN, True)

    def poll(self) -> None:
        """Between frames: a message of the slave's own goes into an empty SM1."""
        if self.state != INIT:
            self._load_mailbox()

    # -- process data ----------------------------------------------------------------------------
    def _cycle(self, outputs: bytes) -> None:
        self.cycles += 1
        inputs = self.app.cycle(outputs if self.state == OP else None)
        area = self._sm_area(INPUTS)
        if area is not None:
            self.memory[area[0]:area[0] + len(inputs)] = inputs[:area[1] - area[0]]
        self._load_mailbox()  # what the cycle raised (an emergency) is in SM1 at once

    # -- the EEPROM ----------------------------------------------------------------------------
    def _eeprom_command(self) -> None:
        control = self.u16(REG_EEPROM_CONTROL)
        command = control & EEPROM_COMMAND_MASK
        status = EEPROM_READ_8_BYTES
        if command == EEPROM_READ:
            word = struct.unpack_from("<I", self.memory, REG_EEPROM_ADDRESS)[0]
            chunk = self.sii[word * 2:word * 2 + 8]
            self.memory[REG_EEPROM_DATA:REG_EEPROM_DATA + 8] = chunk.ljust(8, b"\xff")
        elif command:  # writes and reloads: the emulated EEPROM is read-only
            status |= EEPROM_ERROR_COMMAND
        struct.pack_into("<H", self.memory, REG_EEPROM_CONTROL, status)

    # -- the AL state machine --------------------------------------------------------------------
    def _al_control(self, control: int) -> None:
        requested, ack = control & 0x0F, control & AL_ACK
        status = self.al_status
        current = status & 0x0F
        if status & AL_ERROR and not ack and \
                STATE_ORDER.get(requested, 9) >= STATE_ORDER.get(current, 0):
            return  # an error holds the state until acknowledged (or a step down)
        code = self._refusal(current, requested)
        if code:
            self._set_al(current | AL_ERROR, code)
            return
        if requested != current:
            if requested == INIT:
                self._mailbox_out.clear()
                self._set_sm_status(MAILBOX_IN, False)
            self.app.entered(requested, current)
        self._set_al(requested, 0)

    def _refusal(self, current: int, requested: int) -> int:
        """The AL status code refusing ``current`` -> ``requested`` (0: allowed)."""
        if requested == BOOT:
            return AL_BOOTSTRAP_UNSUPPORTED
        if requested not in STATE_ORDER:
            return AL_UNKNOWN_STATE
        step = STATE_ORDER[requested] - STATE_ORDER[current]
        if step > 1:
            return AL_INVALID_STATE_CHANGE
        if step < 1:
            return 0
        if requested == PRE_OP:
            return self._mailbox_refusal()
        if requested == SAFE_OP:
            return self._process_data_refusal() or self.app.refuse(requested)
        return self.app.refuse(requested)

    def _mailbox_refusal(self) -> int:
        for number, word in ((MAILBOX_OUT, 0x0018), (MAILBOX_IN, 0x001A)):
            start, length = struct.unpack_from("<HH", self.sii, word * 2)
            if self._sm_area(number) != (start, start + length):
                return AL_INVALID_MAILBOX_CONFIG
        return 0

    def _process_data_refusal(self) -> int:
        for number, size, code in ((OUTPUTS, self.app.output_size, AL_INVALID_OUTPUT_CONFIG),
                                   (INPUTS, self.app.input_size, AL_INVALID_INPUT_CONFIG)):
            area = self._sm_area(number)
            if (area[1] - area[0] if area else 0) != size:
                return code
        return 0
