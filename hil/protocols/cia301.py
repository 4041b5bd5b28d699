"""CiA 301 (the CANopen application layer) as data: COB-IDs, NMT, SDO, EMCY, the error
register and the communication objects. One table, read by the drive master, the emulated
node, ``hil drive scan`` and the tests alike; no raw CiA 301 number lives anywhere else.
"""

from __future__ import annotations

from hil.errors import HilError

# -- COB-IDs of the predefined connection set (11-bit): function code + node id -------------
NMT_COB_ID = 0x000
SYNC_COB_ID = 0x080
EMCY_BASE = 0x080
TPDO_BASES = (0x180, 0x280, 0x380, 0x480)
RPDO_BASES = (0x200, 0x300, 0x400, 0x500)
SDO_RESPONSE_BASE = 0x580  # server -> client
SDO_REQUEST_BASE = 0x600   # client -> server
HEARTBEAT_BASE = 0x700
MAX_NODE_ID = 127

# -- NMT: commands (byte 0 of a frame on 0x000) and states (the heartbeat's byte) ----------
NMT_START = 0x01
NMT_STOP = 0x02
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82
NMT_BOOT_UP = 0x00
NMT_STOPPED = 0x04
NMT_OPERATIONAL = 0x05
NMT_PRE_OPERATIONAL = 0x7F
NMT_STATE_NAMES = {NMT_BOOT_UP: "BOOT-UP", NMT_STOPPED: "STOPPED",
                   NMT_OPERATIONAL: "OPERATIONAL", NMT_PRE_OPERATIONAL: "PRE-OPERATIONAL"}

# -- SDO (CiA 301 7.2.4.3): command specifiers of byte 0 and its flags -------------------
SDO_DOWNLOAD_SEGMENT = 0x00    # client: a download segment; server: upload segment answer
SDO_INITIATE_DOWNLOAD = 0x20   # client request
SDO_INITIATE_UPLOAD = 0x40     # client request; also the server's initiate-upload answer
SDO_UPLOAD_SEGMENT = 0x60      # client request; also the server's initiate-download answer
SDO_ABORT = 0x80
SDO_BLOCK_UPLOAD = 0xA0
SDO_BLOCK_DOWNLOAD = 0xC0
SDO_COMMAND_MASK = 0xE0
SDO_SIZE_INDICATED = 0x01
SDO_EXPEDITED = 0x02
SDO_TOGGLE = 0x10
SDO_LAST_SEGMENT = 0x01        # "c" bit of a segment: no more segments

# SDO abort codes
ABORT_TOGGLE = 0x0503_0000
ABORT_TIMEOUT = 0x0504_0000
ABORT_COMMAND = 0x0504_0001
ABORT_UNSUPPORTED = 0x0601_0000
ABORT_WRITE_ONLY = 0x0601_0001
ABORT_READ_ONLY = 0x0601_0002
ABORT_NO_OBJECT = 0x0602_0000
ABORT_CANNOT_MAP = 0x0604_0041
ABORT_PDO_TOO_LONG = 0x0604_0042
ABORT_INCOMPATIBLE = 0x0604_0043
ABORT_LENGTH = 0x0607_0010
ABORT_NO_SUBINDEX = 0x0609_0011
ABORT_VALUE = 0x0609_0030
ABORT_VALUE_HIGH = 0x0609_0031
ABORT_VALUE_LOW = 0x0609_0032
ABORT_GENERAL = 0x0800_0000
ABORT_CANNOT_STORE = 0x0800_0020  # a write the application cannot take (no behaviour for it)
ABORT_DEVICE_STATE = 0x0800_0022
ABORT_NO_DATA = 0x0800_0024       # a read the application has no value for
SDO_ABORT_NAMES = {
    ABORT_TOGGLE: "toggle bit not alternated", ABORT_TIMEOUT: "SDO protocol timed out",
    ABORT_COMMAND: "client/server command specifier not valid or unknown",
    ABORT_UNSUPPORTED: "unsupported access to an object",
    ABORT_WRITE_ONLY: "attempt to read a write only object",
    ABORT_READ_ONLY: "attempt to write a read only object",
    ABORT_NO_OBJECT: "object does not exist in the object dictionary",
    ABORT_CANNOT_MAP: "object cannot be mapped to the PDO",
    ABORT_PDO_TOO_LONG: "the number and length of the objects to be mapped would exceed "
                        "the PDO length",
    ABORT_INCOMPATIBLE: "general parameter incompatibility",
    ABORT_LENGTH: "data type does not match, length of service parameter does not match",
    ABORT_NO_SUBINDEX: "sub-index does not exist",
    ABORT_VALUE: "invalid value for parameter",
    ABORT_VALUE_HIGH: "value of parameter written too high",
    ABORT_VALUE_LOW: "value of parameter written too low",
    ABORT_GENERAL: "general error",
    ABORT_CANNOT_STORE: "data cannot be transferred or stored to the application",
    ABORT_DEVICE_STATE: "data cannot be transferred or stored because of the present device "
                        "state",
    ABORT_NO_DATA: "no data available",
}


def abort_text(code: int) -> str:
    """``"0x06020000 object does not exist in the object dictionary"``."""
    return f"0x{code:08X} {SDO_ABORT_NAMES.get(code, 'unknown abort code')}"


class SdoAbortError(HilError):
    """An SDO transfer aborted with the CiA 301 abort ``code``: raised by a server to refuse a
    request (the emulated drive answers with it), and by a client that received an abort (the
    master; ``context`` names the drive and the object)."""

    def __init__(self, code: int, context: str = "") -> None:
        super().__init__(f"{context}: {abort_text(code)}" if context else abort_text(code))
        self.code = code


# -- EMCY (CiA 301 7.2.7, codes of CiA 301 table 21 and CiA 402) and the error register ----
EMCY_RESET = 0x0000
EMCY_GENERIC = 0x1000
EMCY_OVERCURRENT = 0x2310
EMCY_OVERVOLTAGE = 0x3210
EMCY_OVERTEMPERATURE = 0x4310
EMCY_SOFTWARE = 0x6100
EMCY_COMMUNICATION = 0x8100
EMCY_CAN_OVERRUN = 0x8110
EMCY_CAN_PASSIVE = 0x8120
EMCY_HEARTBEAT = 0x8130
EMCY_BUS_OFF_RECOVERED = 0x8140
EMCY_PDO_LENGTH = 0x8210
EMCY_PDO_TOO_LONG = 0x8220
EMCY_SYNC_LENGTH = 0x8240
EMCY_NAMES = {
    EMCY_RESET: "error reset", EMCY_GENERIC: "generic error",
    EMCY_OVERCURRENT: "continuous over-current", EMCY_OVERVOLTAGE: "DC link over-voltage",
    EMCY_OVERTEMPERATURE: "drive over-temperature", EMCY_SOFTWARE: "internal software error",
    EMCY_COMMUNICATION: "communication error", EMCY_CAN_OVERRUN: "CAN overrun",
    EMCY_CAN_PASSIVE: "CAN error passive", EMCY_HEARTBEAT: "heartbeat or life guard error",
    EMCY_BUS_OFF_RECOVERED: "recovered from bus-off",
    EMCY_PDO_LENGTH: "PDO not processed (length error)",
    EMCY_PDO_TOO_LONG: "PDO length exceeded", EMCY_SYNC_LENGTH: "unexpected SYNC data length",
}


def emcy_text(code: int) -> str:
    """``"0x8130 heartbeat or life guard error"`` (device-specific codes named so)."""
    return f"0x{code:04X} {EMCY_NAMES.get(code, 'device specific')}"


ERR_REG_GENERIC = 0x01
ERR_REG_CURRENT = 0x02
ERR_REG_VOLTAGE = 0x04
ERR_REG_TEMPERATURE = 0x08
ERR_REG_COMMUNICATION = 0x10


def error_register_bit(code: int) -> int:
    """The error register (0x1001) bit of an EMCY code's class (CiA 301, table 48)."""
    return {0x2: ERR_REG_CURRENT, 0x3: ERR_REG_VOLTAGE, 0x4: ERR_REG_TEMPERATURE,
            0x8: ERR_REG_COMMUNICATION}.get(code >> 12, ERR_REG_GENERIC)


# -- the communication profile's objects ------------------------------------------------
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
ERROR_HISTORY = 0x1003          # pre-defined error field
SYNC_COB_ID_OBJECT = 0x1005
CYCLE_PERIOD = 0x1006           # communication cycle period [us]
DEVICE_NAME = 0x1008
CONSUMER_HEARTBEAT = 0x1016
PRODUCER_HEARTBEAT = 0x1017
IDENTITY = 0x1018               # 1 vendor, 2 product, 3 revision, 4 serial
#: 0x1018:5, a sub-index CiA 301 leaves unused, answered by hil's drive emulator only (its own
#: dictionary and every twin, whose 0x1018:1..4 are the vendor's): 'hil' and a format byte.
#: Reading it is harmless on any drive; it tells hil's emulator from a vendor's drive.
HIL_EMULATOR_SUBINDEX, HIL_EMULATOR_SIGNATURE = 5, 0x68696C01
SYNC_COUNTER_OVERFLOW = 0x1019  # 0: SYNC without counter; 2..240: the counter's range
RPDO_COMM_BASE = 0x1400
RPDO_MAP_BASE = 0x1600
TPDO_COMM_BASE = 0x1800
TPDO_MAP_BASE = 0x1A00
