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

# ---------------------------------------------------------- modes of operation (0x6060)
NO_MODE = 0
CYCLIC_SYNCHRONOUS_POSITION = 8
CYCLIC_SYNCHRONOUS_TORQUE = 10
MODES: dict[str, int] = {"csp": CYCLIC_SYNCHRONOUS_POSITION, "cst": CYCLIC_SYNCHRONOUS_TORQUE}
SUPPORTED_MODE_BITS: dict[int, int] = {  # the bit of each mode in 0x6502 (supported modes)
    CYCLIC_SYNCHRONOUS_POSITION: 0x0080,
    CYCLIC_SYNCHRONOUS_TORQUE: 0x0200,
}

# ---------------------------------------------------------------------------- objects
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TARGET_TORQUE = 0x6071
MAX_TORQUE = 0x6072
MAX_CURRENT = 0x6073
RATED_CURRENT = 0x6075
TORQUE_ACTUAL = 0x6077
TARGET_POSITION = 0x607A
POLARITY = 0x607E               # bit 7: position, bit 6: velocity (and torque) reversed
ENCODER_RESOLUTION = 0x608F     # 1: increments, 2: motor revolutions
GEAR_RATIO = 0x6091             # 1: motor revolutions, 2: shaft revolutions
SUPPORTED_MODES = 0x6502
POLARITY_POSITION, POLARITY_VELOCITY = 0x80, 0x40

# -------------------------------------------------------------------- default PDO map
PDO_NOT_VALID = 0x8000_0000  # CiA 301: bit 31 of a PDO's COB-ID

MapEntry = tuple[int, int, int]  # (index, subindex, size in bits)


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


# the target each cyclic synchronous mode reads from RPDO1, after the controlword
CYCLIC_TARGETS: dict[int, MapEntry] = {
    CYCLIC_SYNCHRONOUS_TORQUE: (TARGET_TORQUE, 0, 16),
    CYCLIC_SYNCHRONOUS_POSITION: (TARGET_POSITION, 0, 32),
}
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


def rpdo1_for(mode: int) -> PdoMap:
    """RPDO1 for a cyclic synchronous mode: the controlword and that mode's target."""
    return PdoMap(RPDO1.comm, RPDO1.mapping, RPDO1.cob_base,
                  ((CONTROLWORD, 0, 16), CYCLIC_TARGETS[mode]))
