"""EtherCAT's tables (ETG.1000): the frame and its datagrams, the ESC registers a master and
hil's software slave use, the AL states and status codes, the SII words and categories, the
mailbox and CoE headers. Both sides read them from here: the master
(:mod:`hil.drivers.ethercat`) and the slave (:mod:`hil.emulators.ethercat`)."""

from __future__ import annotations

import struct

ETHERTYPE = 0x88A4          # EtherCAT frames on Ethernet
ETH_HEADER = 14             # destination, source, EtherType
ECAT_HEADER = struct.Struct("<H")  # length (11 bits), reserved, type (4 bits: 1 = commands)
ECAT_TYPE_COMMANDS = 1
DATAGRAM_HEADER = struct.Struct("<BBHHHH")  # command, index, ADP, ADO, length|flags, IRQ
WKC = struct.Struct("<H")
LENGTH_MASK, CIRCULATING, MORE = 0x07FF, 0x4000, 0x8000

# datagram commands
NOP, APRD, APWR, APRW, FPRD, FPWR, FPRW, BRD, BWR, BRW, LRD, LWR, LRW, ARMW, FRMW = range(15)
AUTO_INCREMENT = (APRD, APWR, APRW, ARMW)
CONFIGURED = (FPRD, FPWR, FPRW, FRMW)
BROADCAST = (BRD, BWR, BRW)
LOGICAL = (LRD, LWR, LRW)
READS = (APRD, FPRD, BRD, LRD)
WRITES = (APWR, FPWR, BWR, LWR)
READ_WRITES = (APRW, FPRW, BRW, LRW)
COMMAND_NAMES = ("NOP", "APRD", "APWR", "APRW", "FPRD", "FPWR", "FPRW", "BRD", "BWR", "BRW",
                 "LRD", "LWR", "LRW", "ARMW", "FRMW")

# ESC registers (ET1100 numbering)
REG_TYPE, REG_REVISION, REG_BUILD = 0x0000, 0x0001, 0x0002
REG_FMMUS, REG_SYNC_MANAGERS, REG_RAM_SIZE, REG_PORTS = 0x0004, 0x0005, 0x0006, 0x0007
REG_FEATURES = 0x0008
REG_STATION_ADDRESS, REG_STATION_ALIAS = 0x0010, 0x0012
REG_DL_CONTROL, REG_DL_STATUS = 0x0100, 0x0110
REG_AL_CONTROL, REG_AL_STATUS, REG_AL_STATUS_CODE = 0x0120, 0x0130, 0x0134
REG_PDI_CONTROL = 0x0140
REG_EEPROM_CONFIG, REG_EEPROM_CONTROL, REG_EEPROM_ADDRESS, REG_EEPROM_DATA = \
    0x0500, 0x0502, 0x0504, 0x0508
REG_FMMU0, FMMU_SIZE = 0x0600, 16
REG_SM0, SM_SIZE = 0x0800, 8
REG_DC_RECEIVE_TIMES, REG_DC_SYSTEM_TIME, REG_DC_RECEIVE_TIME_UNIT = 0x0900, 0x0910, 0x0918
REG_DC_SYSTEM_OFFSET, REG_DC_SYSTEM_DELAY = 0x0920, 0x0928
REG_DC_SYNC_ACTIVATION, REG_DC_START_TIME, REG_DC_SYNC0_CYCLE = 0x0981, 0x0990, 0x09A0
PROCESS_RAM = 0x1000        # the ESC's process memory starts here

FEATURE_DC, FEATURE_DC64 = 0x0004, 0x0008

# FMMU registers: logical start, length, start bit, end bit, physical start, start bit, type,
# activate
FMMU = struct.Struct("<IHBBHBBB3x")
FMMU_READ, FMMU_WRITE = 1, 2
# SyncManager registers: physical start, length, control, status, activate, PDI control
SYNC_MANAGER = struct.Struct("<HHBBBB")
SM_STATUS_MAILBOX_FULL = 0x08
SM_ACTIVATE_ENABLE = 0x01

# AL states (register 0x0120 / 0x0130, low four bits) and the error flag
INIT, PRE_OP, BOOT, SAFE_OP, OP = 0x01, 0x02, 0x03, 0x04, 0x08
AL_ERROR, AL_ACK = 0x10, 0x10
AL_STATE_NAMES = {INIT: "INIT", PRE_OP: "PRE-OP", BOOT: "BOOT", SAFE_OP: "SAFE-OP", OP: "OP"}

# AL status codes (ETG.1000.6, table 11)
AL_NO_ERROR = 0x0000
AL_UNSPECIFIED = 0x0001
AL_INVALID_STATE_CHANGE = 0x0011
AL_UNKNOWN_STATE = 0x0012
AL_BOOTSTRAP_UNSUPPORTED = 0x0013
AL_INVALID_MAILBOX_CONFIG = 0x0016
AL_SYNC_WATCHDOG = 0x001B
AL_INVALID_OUTPUT_CONFIG = 0x001D
AL_INVALID_INPUT_CONFIG = 0x001E
AL_STATUS_CODES = {
    AL_NO_ERROR: "no error", AL_UNSPECIFIED: "unspecified error",
    AL_INVALID_STATE_CHANGE: "invalid requested state change",
    AL_UNKNOWN_STATE: "unknown requested state",
    AL_BOOTSTRAP_UNSUPPORTED: "bootstrap not supported",
    AL_INVALID_MAILBOX_CONFIG: "invalid mailbox configuration",
    AL_SYNC_WATCHDOG: "sync manager watchdog",
    AL_INVALID_OUTPUT_CONFIG: "invalid output configuration",
    AL_INVALID_INPUT_CONFIG: "invalid input configuration",
}


def al_state_text(status: int) -> str:
    """``SAFE-OP`` of 0x04, ``PRE-OP + ERROR`` of 0x12."""
    name = AL_STATE_NAMES.get(status & 0x0F, f"state 0x{status & 0x0F:X}")
    return name + (" + ERROR" if status & AL_ERROR else "")


def al_status_text(code: int) -> str:
    """``0x001D invalid output configuration``."""
    return f"0x{code:04X} {AL_STATUS_CODES.get(code, 'vendor-specific')}"


# EEPROM (SII) interface: control/status bits
EEPROM_READ, EEPROM_WRITE, EEPROM_RELOAD = 0x0100, 0x0200, 0x0400
EEPROM_COMMAND_MASK = 0x0700
EEPROM_READ_8_BYTES = 0x0040
EEPROM_ERROR_COMMAND, EEPROM_BUSY = 0x2000, 0x8000

# SII words (word addresses) and categories
SII_VENDOR, SII_PRODUCT, SII_REVISION, SII_SERIAL = 0x0008, 0x000A, 0x000C, 0x000E
SII_RX_MAILBOX, SII_TX_MAILBOX, SII_MAILBOX_PROTOCOLS = 0x0018, 0x001A, 0x001C
SII_SIZE, SII_VERSION, SII_CATEGORIES = 0x003E, 0x003F, 0x0040
CAT_STRINGS, CAT_GENERAL, CAT_FMMU, CAT_SYNC_MANAGER = 10, 30, 40, 41
CAT_TXPDO, CAT_RXPDO, CAT_END = 50, 51, 0xFFFF
MAILBOX_COE = 0x0004
# CoE details of the general category: SDO, PDO assignment, PDO configuration
COE_SDO, COE_SDO_INFO, COE_PDO_ASSIGN, COE_PDO_CONFIG, COE_COMPLETE_ACCESS = \
    0x01, 0x02, 0x04, 0x08, 0x20
FMMU_USE_OUTPUTS, FMMU_USE_INPUTS, FMMU_USE_MAILBOX_STATE = 1, 2, 3
SM_TYPE_MAILBOX_OUT, SM_TYPE_MAILBOX_IN, SM_TYPE_OUTPUTS, SM_TYPE_INPUTS = 1, 2, 3, 4

# the mailbox: its header, and CoE's
MAILBOX_HEADER = struct.Struct("<HHBB")  # length, address, channel/priority, type/counter
MAILBOX_TYPE_ERROR, MAILBOX_TYPE_COE = 0x00, 0x03
MAILBOX_ERROR_UNSUPPORTED_PROTOCOL = 0x0002
COE_HEADER = struct.Struct("<H")         # number (9 bits), reserved, service (4 bits)
COE_EMERGENCY, COE_SDO_REQUEST, COE_SDO_RESPONSE = 1, 2, 3
SDO_HEADER = struct.Struct("<BHB")       # command, index, sub-index
EMERGENCY = struct.Struct("<HB5s")       # error code, error register, data

# the SyncManager communication types and PDO assignments (ETG.1020, CiA 402 over EtherCAT)
SM_COMM_TYPES, RXPDO_ASSIGN, TXPDO_ASSIGN = 0x1C00, 0x1C12, 0x1C13
RXPDO_MAPPINGS, TXPDO_MAPPINGS = range(0x1600, 0x1800), range(0x1A00, 0x1C00)
