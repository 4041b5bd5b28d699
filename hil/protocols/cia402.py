"""The CiA 402 drive profile as data: states, controlword commands, statusword masks, the state
chart's transitions, modes of operation and the default PDO map.

Written once, in the style of ``canopen.profiles.p402``, and read by the master
(:mod:`hil.drivers.canopen`), the emulated drive (:mod:`hil.emulators.drive.node`, whose state
machine walks :data:`TRANSITIONS`) and the tests (``tests/protocols/test_cia402.py`` checks the
tables against canopen's ``State402``). Transition numbers are those of the CiA 402 state chart.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

# -------------------------------------------------------------------------------- states
NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY_TO_SWITCH_ON = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
FAULT = "FAULT"

# --------------------------------------------------------------------- statusword (0x6041)
# state -> (mask, value): the state is the one whose masked bits equal its value
STATUSWORD_MASKS: dict[str, tuple[int, int]] = {
    NOT_READY_TO_SWITCH_ON: (0x4F, 0x00),
    SWITCH_ON_DISABLED: (0x4F, 0x40),
    READY_TO_SWITCH_ON: (0x6F, 0x21),
    SWITCHED_ON: (0x6F, 0x23),
    OPERATION_ENABLED: (0x6F, 0x27),
    QUICK_STOP_ACTIVE: (0x6F, 0x07),
    FAULT_REACTION_ACTIVE: (0x4F, 0x0F),
    FAULT: (0x4F, 0x08),
}
SW_VOLTAGE_ENABLED = 0x0010
SW_WARNING = 0x0080
SW_REMOTE = 0x0200
SW_INTERNAL_LIMIT = 0x0800
SW_FOLLOWS_COMMAND = 0x1000  # cyclic synchronous modes: the drive follows the command value
UNKNOWN_STATE = "UNKNOWN"


@lru_cache(maxsize=1024)  # read every cycle; a drive shows a handful of statuswords
def state_of(statusword: int) -> str:
    """The state a statusword reports (``UNKNOWN`` if none matches)."""
    for state, (mask, value) in STATUSWORD_MASKS.items():
        if statusword & mask == value:
            return state
    return UNKNOWN_STATE


# ------------------------------------------------------------------- controlword (0x6040)
DISABLE_VOLTAGE = "DISABLE VOLTAGE"
QUICK_STOP = "QUICK STOP"
SHUTDOWN = "SHUTDOWN"
SWITCH_ON = "SWITCH ON"                 # also "disable operation" (same bits)
ENABLE_OPERATION = "ENABLE OPERATION"   # also "switch on + enable operation" (same bits)
FAULT_RESET = "FAULT RESET"             # the rising edge of bit 7

# command -> the controlword a master sends for it
CONTROLWORDS: dict[str, int] = {
    DISABLE_VOLTAGE: 0x0000,
    QUICK_STOP: 0x0002,
    SHUTDOWN: 0x0006,
    SWITCH_ON: 0x0007,
    ENABLE_OPERATION: 0x000F,
    FAULT_RESET: 0x0080,
}
CW_DISABLE_VOLTAGE = CONTROLWORDS[DISABLE_VOLTAGE]
CW_QUICK_STOP = CONTROLWORDS[QUICK_STOP]
CW_SHUTDOWN = CONTROLWORDS[SHUTDOWN]
CW_SWITCH_ON = CONTROLWORDS[SWITCH_ON]
CW_ENABLE_OPERATION = CONTROLWORDS[ENABLE_OPERATION]
CW_FAULT_RESET = CONTROLWORDS[FAULT_RESET]

# command -> (mask, value) of the bits that encode it (bit 7 low: no fault reset pending)
CONTROLWORD_MASKS: dict[str, tuple[int, int]] = {
    DISABLE_VOLTAGE: (0x82, 0x00),
    QUICK_STOP: (0x86, 0x02),
    SHUTDOWN: (0x87, 0x06),
    SWITCH_ON: (0x8F, 0x07),
    ENABLE_OPERATION: (0x8F, 0x0F),
}


@lru_cache(maxsize=1024)  # the drive reads one every cycle; few distinct pairs occur
def command_of(controlword: int, previous: int = 0) -> str | None:
    """The command a controlword gives after ``previous``: FAULT RESET on a rising edge of bit
    7, none while bit 7 stays high, else the one command whose bits match."""
    if controlword & CW_FAULT_RESET:
        return None if previous & CW_FAULT_RESET else FAULT_RESET
    for command, (mask, value) in CONTROLWORD_MASKS.items():
        if controlword & mask == value:
            return command
    raise ValueError(f"controlword 0x{controlword:04X} encodes no CiA 402 command")


# ---------------------------------------------------------------------------- state chart
# (state, command) -> the transitions the command makes, in order: (number, next state).
# Automatic ones are not commands: 0 and 1 at power-on, 12 at the end of a quick stop with
# option 1 or 2, 13 on a fault, 14 at the end of the fault reaction.
TRANSITIONS: dict[tuple[str, str], tuple[tuple[int, str], ...]] = {
    (SWITCH_ON_DISABLED, SHUTDOWN): ((2, READY_TO_SWITCH_ON),),
    (READY_TO_SWITCH_ON, SWITCH_ON): ((3, SWITCHED_ON),),
    (READY_TO_SWITCH_ON, ENABLE_OPERATION): ((3, SWITCHED_ON), (4, OPERATION_ENABLED)),
    (SWITCHED_ON, ENABLE_OPERATION): ((4, OPERATION_ENABLED),),
    (OPERATION_ENABLED, SWITCH_ON): ((5, SWITCHED_ON),),           # disable operation
    (SWITCHED_ON, SHUTDOWN): ((6, READY_TO_SWITCH_ON),),
    (READY_TO_SWITCH_ON, DISABLE_VOLTAGE): ((7, SWITCH_ON_DISABLED),),
    (READY_TO_SWITCH_ON, QUICK_STOP): ((7, SWITCH_ON_DISABLED),),
    (OPERATION_ENABLED, SHUTDOWN): ((8, READY_TO_SWITCH_ON),),
    (OPERATION_ENABLED, DISABLE_VOLTAGE): ((9, SWITCH_ON_DISABLED),),
    (SWITCHED_ON, DISABLE_VOLTAGE): ((10, SWITCH_ON_DISABLED),),
    (SWITCHED_ON, QUICK_STOP): ((10, SWITCH_ON_DISABLED),),
    (OPERATION_ENABLED, QUICK_STOP): ((11, QUICK_STOP_ACTIVE),),
    (QUICK_STOP_ACTIVE, DISABLE_VOLTAGE): ((12, SWITCH_ON_DISABLED),),
    (FAULT, FAULT_RESET): ((15, SWITCH_ON_DISABLED),),
    (QUICK_STOP_ACTIVE, ENABLE_OPERATION): ((16, OPERATION_ENABLED),),  # options 5..8 only
}

# the next state on the way to OPERATION ENABLED (canopen's NEXTSTATE2ANY)
NEXT_STATE_TO_ENABLE: dict[str, str] = {
    NOT_READY_TO_SWITCH_ON: SWITCH_ON_DISABLED,
    FAULT_REACTION_ACTIVE: FAULT,
    FAULT: SWITCH_ON_DISABLED,
    QUICK_STOP_ACTIVE: SWITCH_ON_DISABLED,
    SWITCH_ON_DISABLED: READY_TO_SWITCH_ON,
    READY_TO_SWITCH_ON: SWITCHED_ON,
    SWITCHED_ON: OPERATION_ENABLED,
}


def command_to(source: str, target: str) -> str:
    """The command whose transitions lead from ``source`` to ``target`` in one step."""
    for (state, command), steps in TRANSITIONS.items():
        if state == source and len(steps) == 1 and steps[0][1] == target:
            return command
    raise KeyError(f"no CiA 402 command leads from {source} to {target}")


def enable_steps(start: str = SWITCH_ON_DISABLED) -> tuple[tuple[int, str], ...]:
    """(controlword, state it leads to) from ``start`` to OPERATION ENABLED, one step each."""
    steps = []
    state = start
    while state != OPERATION_ENABLED:
        target = NEXT_STATE_TO_ENABLE[state]
        steps.append((CONTROLWORDS[command_to(state, target)], target))
        state = target
    return tuple(steps)


# ------------------------------------------------------- quick stop option code (0x605A)
# the options this package uses (3, 4, 7, 8, stopping on the current or voltage limit, not)
QUICK_STOP_OPTIONS: dict[int, str] = {
    0: "disable the drive function",
    1: "slow-down ramp, then SWITCH ON DISABLED",
    2: "quick-stop ramp, then SWITCH ON DISABLED",
    5: "slow-down ramp, then stay in QUICK STOP ACTIVE",
    6: "quick-stop ramp, then stay in QUICK STOP ACTIVE",
}
QUICK_STOP_THEN_DISABLED = (1, 2, 3, 4)  # options ending in SWITCH ON DISABLED (transition 12)
QUICK_STOP_STAYS = (5, 6, 7, 8)          # options staying in QUICK STOP ACTIVE (16 allowed)

# ------------------------------------------------------------ mode-specific bits
# controlword bits 4..6 and 8 mean what the mode of operation says (CiA 402)
CW_NEW_SET_POINT = 0x0010         # PP: a new target position (rising edge)
CW_HOMING_START = 0x0010          # HM: start homing (rising edge; falling: interrupt)
CW_CHANGE_SET_IMMEDIATELY = 0x0020  # PP: the new target replaces the one under way
CW_RELATIVE = 0x0040              # PP: the target is relative to the last one
CW_HALT = 0x0100                  # PP, PV, HM: stop with the profile deceleration
# statusword bits 10, 12 and 13 too
SW_TARGET_REACHED = 0x0400        # PP, PV, HM (and set on a halt once standing)
SW_SET_POINT_ACK = 0x1000         # PP: the new set point was taken
SW_SPEED_ZERO = 0x1000            # PV: the speed is zero
SW_HOMING_ATTAINED = 0x1000       # HM: homing completed
SW_FOLLOWING_ERROR = 0x2000       # PP, CSP: beyond the following error window
SW_HOMING_ERROR = 0x2000          # HM: homing failed
SW_MODE_BITS = SW_TARGET_REACHED | SW_FOLLOWS_COMMAND | SW_FOLLOWING_ERROR

# ---------------------------------------------------------------------------- objects
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_DISPLAY = 0x6061
POSITION_DEMAND = 0x6062
POSITION_ACTUAL = 0x6064
FOLLOWING_ERROR_WINDOW = 0x6065   # UNSIGNED32 [increments]
POSITION_WINDOW = 0x6067          # UNSIGNED32 [increments]: PP's "target reached" band
POSITION_WINDOW_TIME = 0x6068     # UNSIGNED16 [ms]
VELOCITY_DEMAND = 0x606B
VELOCITY_ACTUAL = 0x606C
VELOCITY_WINDOW = 0x606D          # UNSIGNED16 [increments/s]: PV's "target reached" band
VELOCITY_WINDOW_TIME = 0x606E     # UNSIGNED16 [ms]
VELOCITY_THRESHOLD = 0x606F       # UNSIGNED16 [increments/s]: PV's "speed zero" band
TARGET_TORQUE = 0x6071
MAX_TORQUE = 0x6072
MAX_CURRENT = 0x6073
RATED_CURRENT = 0x6075
TORQUE_ACTUAL = 0x6077
TARGET_POSITION = 0x607A
HOME_OFFSET = 0x607C              # INTEGER32 [increments]: the home position's value
POLARITY = 0x607E               # bit 7: position, bit 6: velocity (and torque) reversed
PROFILE_VELOCITY = 0x6081         # UNSIGNED32 [increments/s]
PROFILE_ACCELERATION = 0x6083     # UNSIGNED32 [increments/s^2]
PROFILE_DECELERATION = 0x6084     # UNSIGNED32 [increments/s^2]
QUICK_STOP_DECELERATION = 0x6085  # UNSIGNED32 [increments/s^2]
ENCODER_RESOLUTION = 0x608F     # 1: increments, 2: motor revolutions
GEAR_RATIO = 0x6091             # 1: motor revolutions, 2: shaft revolutions
HOMING_METHOD = 0x6098            # INTEGER8
HOMING_SPEEDS = 0x6099            # 1: switch search, 2: zero search, UNSIGNED32 [increments/s]
HOMING_ACCELERATION = 0x609A      # UNSIGNED32 [increments/s^2]
DIGITAL_INPUTS = 0x60FD           # UNSIGNED32: bit 0 negative limit, 1 positive limit, 2 home
TARGET_VELOCITY = 0x60FF          # INTEGER32 [increments/s]
SUPPORTED_MODES = 0x6502
POLARITY_POSITION, POLARITY_VELOCITY = 0x80, 0x40
DI_NEGATIVE_LIMIT, DI_POSITIVE_LIMIT, DI_HOME_SWITCH = 0x1, 0x2, 0x4

MapEntry = tuple[int, int, int]  # (index, subindex, size in bits)

# ---------------------------------------------------------- modes of operation (0x6060)
NO_MODE = 0
PROFILE_POSITION_MODE = 1
PROFILE_VELOCITY_MODE = 3
HOMING_MODE = 6
CYCLIC_SYNCHRONOUS_POSITION = 8
CYCLIC_SYNCHRONOUS_VELOCITY = 9
CYCLIC_SYNCHRONOUS_TORQUE = 10
#: CiA 402's short name of every mode of operation, by code
MODE_SHORT_NAMES: dict[int, str] = {1: "PP", 2: "VL", 3: "PV", 4: "TQ", 6: "HM", 7: "IP",
                                    8: "CSP", 9: "CSV", 10: "CST"}


def supported_mode_bit(code: int) -> int:
    """The bit of mode ``code`` in 0x6502: bit n-1 for modes 1..10 (CiA 402)."""
    return 1 << (code - 1)


@dataclass(frozen=True)
class OperationMode:
    """One mode of operation as a master drives it: everything that differs between modes
    is here, so the master and the emulated drive branch on data, not on the mode.

    ``set_point``: the object the master sends after the controlword in RPDO1 every cycle
    (None: the controlword alone, homing); ``unit``: the set point's unit on hil's side
    (``deg``, ``deg/s``, ``mA``; None: none); ``cyclic``: the drive follows a set point sent
    every SYNC (statusword bit 12 "follows the command"), else it runs a profile of its own
    towards a target (PP, PV) or a homing; ``profile``: the objects that shape that profile,
    written at configure; ``status_bits``: what statusword bits 10, 12 and 13 mean in it."""

    name: str
    code: int
    title: str
    set_point: MapEntry | None
    unit: str | None
    cyclic: bool
    profile: tuple[tuple[int, int], ...] = ()
    status_bits: tuple[tuple[int, str], ...] = ()

    @property
    def short(self) -> str:
        return MODE_SHORT_NAMES[self.code]

    @property
    def supported_bit(self) -> int:
        return supported_mode_bit(self.code)

    def rpdo1(self) -> PdoMap:
        """RPDO1 in this mode: the controlword, then the set point (if the mode has one)."""
        entries = ((CONTROLWORD, 0, 16),) + ((self.set_point,) if self.set_point else ())
        return PdoMap(RPDO1.comm, RPDO1.mapping, RPDO1.cob_base, entries)


_FOLLOWS = ((12, "follows the command"), (13, "following error"))
PROFILE_MOVE = ((PROFILE_VELOCITY, 0), (PROFILE_ACCELERATION, 0), (PROFILE_DECELERATION, 0))
#: every mode hil drives, by the name ``[master] mode`` and the command line give
OPERATION_MODES: dict[str, OperationMode] = {mode.name: mode for mode in (
    OperationMode("pp", PROFILE_POSITION_MODE, "profile position", (TARGET_POSITION, 0, 32),
                  "deg", False, PROFILE_MOVE,
                  ((10, "target reached"), (12, "set-point acknowledge"),
                   (13, "following error"))),
    OperationMode("pv", PROFILE_VELOCITY_MODE, "profile velocity", (TARGET_VELOCITY, 0, 32),
                  "deg/s", False, PROFILE_MOVE[1:],
                  ((10, "target reached"), (12, "speed zero"), (13, "max slippage"))),
    OperationMode("hm", HOMING_MODE, "homing", None, None, False,
                  ((HOMING_METHOD, 0), (HOME_OFFSET, 0), (HOMING_SPEEDS, 1), (HOMING_SPEEDS, 2),
                   (HOMING_ACCELERATION, 0)),
                  ((10, "target reached"), (12, "homing attained"), (13, "homing error"))),
    OperationMode("csp", CYCLIC_SYNCHRONOUS_POSITION, "cyclic synchronous position",
                  (TARGET_POSITION, 0, 32), "deg", True, (), ((10, "status toggle"), *_FOLLOWS)),
    OperationMode("csv", CYCLIC_SYNCHRONOUS_VELOCITY, "cyclic synchronous velocity",
                  (TARGET_VELOCITY, 0, 32), "deg/s", True, (),
                  ((10, "status toggle"), (12, "follows the command"))),
    OperationMode("cst", CYCLIC_SYNCHRONOUS_TORQUE, "cyclic synchronous torque",
                  (TARGET_TORQUE, 0, 16), "mA", True, (),
                  ((10, "status toggle"), (12, "follows the command"))),
)}


@dataclass(frozen=True)
class ProfileObject:
    """An object that shapes a mode's profile or homing (:attr:`OperationMode.profile`): what
    it is, its unit on hil's side (``deg``, ``deg/s``, ``deg/s^2``; "" a plain number, the
    homing method: the drive's are increments, increments/s, increments/s^2) and its wire
    format."""

    title: str
    unit: str
    fmt: str

    @property
    def bits(self) -> int:
        return {"b": 8, "h": 16, "H": 16, "i": 32, "I": 32}[self.fmt[-1]]


#: every object of a mode's ``profile``, by (index, sub-index)
PROFILE_OBJECTS: dict[tuple[int, int], ProfileObject] = {
    (PROFILE_VELOCITY, 0): ProfileObject("profile velocity", "deg/s", "<I"),
    (PROFILE_ACCELERATION, 0): ProfileObject("profile acceleration", "deg/s^2", "<I"),
    (PROFILE_DECELERATION, 0): ProfileObject("profile deceleration", "deg/s^2", "<I"),
    (HOMING_METHOD, 0): ProfileObject("homing method", "", "<b"),
    (HOME_OFFSET, 0): ProfileObject("home offset", "deg", "<i"),
    (HOMING_SPEEDS, 1): ProfileObject("homing speed while searching for the switch", "deg/s",
                                      "<I"),
    (HOMING_SPEEDS, 2): ProfileObject("homing speed while searching for zero", "deg/s", "<I"),
    (HOMING_ACCELERATION, 0): ProfileObject("homing acceleration", "deg/s^2", "<I"),
}
#: the modes by their 0x6060 code
MODES_BY_CODE: dict[int, OperationMode] = {mode.code: mode for mode in OPERATION_MODES.values()}
# the older names, kept as views of the table
MODES: dict[str, int] = {name: mode.code for name, mode in OPERATION_MODES.items()}
SUPPORTED_MODE_BITS: dict[int, int] = {mode.code: mode.supported_bit
                                       for mode in OPERATION_MODES.values()}


def mode_switch_allowed(state: str, current: OperationMode | None, target: OperationMode,
                        standing: bool) -> bool:
    """Whether a master may switch 0x6060 from ``current`` to ``target`` now. CiA 402 lets a
    drive change modes in any state, but only a standing axis may change what it follows:
    outside OPERATION ENABLED always; in it, only between modes whose set points are alike
    (cyclic to cyclic) and with the axis standing (``standing``: below the standstill speed)."""
    if state != OPERATION_ENABLED or current is None or current == target:
        return True
    return standing and current.cyclic == target.cyclic


# --------------------------------------------------------------------- homing (0x6098)
@dataclass(frozen=True)
class HomingMethod:
    """One CiA 402 homing method: where it searches first (``direction`` -1 / +1; 0: no
    move), the switch whose edge it looks for (``switch``: a DI_* bit of 0x60FD, 0: none),
    and whether home is the first index pulse after that edge (``index``) or the edge itself.
    Home is then ``0x607C`` home offset."""

    number: int
    direction: int
    switch: int
    index: bool
    text: str


#: the homing methods hil knows, by number (CiA 402 section "homing mode")
HOMING_METHODS: dict[int, HomingMethod] = {m.number: m for m in (
    HomingMethod(1, -1, DI_NEGATIVE_LIMIT, True, "negative limit switch and index pulse"),
    HomingMethod(2, +1, DI_POSITIVE_LIMIT, True, "positive limit switch and index pulse"),
    HomingMethod(17, -1, DI_NEGATIVE_LIMIT, False, "negative limit switch"),
    HomingMethod(18, +1, DI_POSITIVE_LIMIT, False, "positive limit switch"),
    HomingMethod(33, -1, 0, True, "index pulse in the negative direction"),
    HomingMethod(34, +1, 0, True, "index pulse in the positive direction"),
    HomingMethod(35, 0, 0, False, "current position (before CiA 402 v4: 37)"),
    HomingMethod(37, 0, 0, False, "current position"),
)}

# -------------------------------------------------------------------- default PDO map
PDO_NOT_VALID = 0x8000_0000  # CiA 301: bit 31 of a PDO's COB-ID

def mapping_entry(index: int, subindex: int, bits: int) -> int:
    """The UNSIGNED32 value of one PDO mapping entry (CiA 301)."""
    return (index << 16) | (subindex << 8) | bits


@dataclass(frozen=True)
class PdoMap:
    """One PDO: its communication and mapping objects, COB-ID base and mapped objects."""

    comm: int                        # communication parameter (0x1400.. RPDO, 0x1800.. TPDO)
    mapping: int                     # mapping parameter (0x1600.., 0x1A00..)
    cob_base: int                    # COB-ID = cob_base + node id
    entries: tuple[MapEntry, ...]

    def cob_id(self, node_id: int) -> int:
        return self.cob_base + node_id

    def mapping_values(self) -> list[int]:
        """The mapping object's sub-indices 1..n as written by SDO."""
        return [mapping_entry(*entry) for entry in self.entries]

    @property
    def size_bytes(self) -> int:
        return sum(bits for _, _, bits in self.entries) // 8


RPDO1 = PdoMap(0x1400, 0x1600, 0x200, ((CONTROLWORD, 0, 16), (TARGET_TORQUE, 0, 16)))
TPDO1 = PdoMap(0x1800, 0x1A00, 0x180, ((STATUSWORD, 0, 16), (POSITION_ACTUAL, 0, 32)))
TPDO2 = PdoMap(0x1801, 0x1A01, 0x280, ((VELOCITY_ACTUAL, 0, 32), (TORQUE_ACTUAL, 0, 16)))
RPDOS = (RPDO1,)
TPDOS = (TPDO1, TPDO2)
# one 8-byte TPDO per cycle instead of two (a busy bus): what Feedback needs but the velocity,
# which the master then derives from the position, cycle by cycle
TPDO1_ALONE = PdoMap(0x1800, 0x1A00, 0x180, ((STATUSWORD, 0, 16), (POSITION_ACTUAL, 0, 32),
                                             (TORQUE_ACTUAL, 0, 16)))
#: ``[master] tpdo_layout``: the TPDOs each cycle's feedback comes in
TPDO_LAYOUTS: dict[str, tuple[PdoMap, ...]] = {"two": TPDOS, "one": (TPDO1_ALONE,)}

