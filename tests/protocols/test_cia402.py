"""The CiA 402 tables (hil/protocols/cia402.py) against an independent statement of the standard:
canopen's ``State402`` and ``OperationMode`` (canopen/profiles/p402.py)."""

import pytest
from canopen.profiles.p402 import OperationMode, State402

from hil.protocols import cia402


def test_statusword_masks_and_values_are_canopens_for_every_state():
    assert cia402.STATUSWORD_MASKS == State402.SW_MASK


@pytest.mark.parametrize("state", list(State402.SW_MASK))
def test_state_of_reads_every_state_and_nothing_else(state):
    _mask, value = State402.SW_MASK[state]
    others = 0xFF90  # voltage enabled, warning, remote, mode-specific...: in no state's mask
    assert cia402.state_of(value) == state
    assert cia402.state_of(value | others) == state
    assert [s for s, (m, v) in State402.SW_MASK.items() if value & m == v] == [state]
    assert cia402.state_of(0x004F) == cia402.UNKNOWN_STATE


def test_controlword_commands_are_canopens():
    assert cia402.CW_DISABLE_VOLTAGE == State402.CW_DISABLE_VOLTAGE
    assert cia402.CW_QUICK_STOP == State402.CW_QUICK_STOP
    assert cia402.CW_SHUTDOWN == State402.CW_SHUTDOWN
    assert cia402.CW_SWITCH_ON == State402.CW_SWITCH_ON
    assert cia402.CW_ENABLE_OPERATION == State402.CW_OPERATION_ENABLED
    assert cia402.CW_FAULT_RESET == State402.CW_SWITCH_ON_DISABLED  # canopen's name for 15


def test_every_controlword_decodes_to_one_command():
    for word in range(0x100):
        if word & 0x80:
            assert cia402.command_of(word, previous=0) == cia402.FAULT_RESET
            assert cia402.command_of(word, previous=0x80) is None  # held high: no new command
            continue
        matching = [c for c, (m, v) in cia402.CONTROLWORD_MASKS.items() if word & m == v]
        assert matching == [cia402.command_of(word)], hex(word)
    for command, word in cia402.CONTROLWORDS.items():
        assert cia402.command_of(word) == command


def test_transitions_cover_canopens_transition_table():
    """canopen's TRANSITIONTABLE: (from, to) -> the controlword a master sends for the step."""
    for (source, command), steps in cia402.TRANSITIONS.items():
        if len(steps) == 1:
            target = steps[0][1]
            theirs = cia402.command_of(State402.TRANSITIONTABLE[(source, target)])
            assert cia402.TRANSITIONS[(source, theirs)] == steps, (source, command)
    commanded = {(s, steps[0][1]) for (s, _), steps in cia402.TRANSITIONS.items()
                 if len(steps) == 1}
    automatic = {(s, t) for (s, t), word in State402.TRANSITIONTABLE.items()
                 if word == 0 and "START" not in (s, t) and (s, t) not in commanded}
    assert automatic == {("NOT READY TO SWITCH ON", "SWITCH ON DISABLED"),  # 1
                         ("FAULT REACTION ACTIVE", "FAULT")}                 # 14
    assert commanded | automatic == {k for k in State402.TRANSITIONTABLE if "START" not in k}


def test_transition_numbers_are_the_state_charts():
    numbers = sorted(n for steps in cia402.TRANSITIONS.values() for n, _ in steps)
    assert set(numbers) == {2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 15, 16}  # 0, 1, 13, 14 automatic
    assert cia402.TRANSITIONS[(cia402.READY_TO_SWITCH_ON, cia402.ENABLE_OPERATION)] == (
        (3, cia402.SWITCHED_ON), (4, cia402.OPERATION_ENABLED))


def test_next_state_to_enable_follows_canopen():
    for state, following in cia402.NEXT_STATE_TO_ENABLE.items():
        assert State402.next_state_indirect(state) == following


def test_enable_steps_walk_from_switch_on_disabled_to_operation_enabled():
    assert cia402.enable_steps() == (
        (State402.CW_SHUTDOWN, "READY TO SWITCH ON"),
        (State402.CW_SWITCH_ON, "SWITCHED ON"),
        (State402.CW_OPERATION_ENABLED, "OPERATION ENABLED"))
    assert cia402.enable_steps(cia402.FAULT)[0] == (State402.CW_SWITCH_ON_DISABLED,
                                                    "SWITCH ON DISABLED")
    with pytest.raises(KeyError, match="no CiA 402 command"):
        cia402.command_to(cia402.SWITCH_ON_DISABLED, cia402.OPERATION_ENABLED)


def test_mode_codes_and_supported_mode_bits_are_canopens():
    assert cia402.MODES == {"pp": OperationMode.PROFILED_POSITION,
                            "pv": OperationMode.PROFILED_VELOCITY,
                            "hm": OperationMode.HOMING,
                            "csp": OperationMode.CYCLIC_SYNCHRONOUS_POSITION,
                            "csv": OperationMode.CYCLIC_SYNCHRONOUS_VELOCITY,
                            "cst": OperationMode.CYCLIC_SYNCHRONOUS_TORQUE}
    assert cia402.NO_MODE == OperationMode.NO_MODE
    for mode, bit in cia402.SUPPORTED_MODE_BITS.items():
        assert OperationMode.SUPPORTED[OperationMode.CODE2NAME[mode]] == bit
    for code, short in cia402.MODE_SHORT_NAMES.items():
        assert cia402.supported_mode_bit(code) == OperationMode.SUPPORTED[
            OperationMode.CODE2NAME[code]], short


def test_a_standing_axis_switches_between_modes_alike_only():
    modes = cia402.OPERATION_MODES
    enabled = cia402.OPERATION_ENABLED
    assert cia402.mode_switch_allowed(cia402.SWITCH_ON_DISABLED, modes["cst"], modes["pp"],
                                      standing=False)
    assert cia402.mode_switch_allowed(enabled, modes["cst"], modes["csp"], standing=True)
    assert not cia402.mode_switch_allowed(enabled, modes["cst"], modes["csp"], standing=False)
    assert not cia402.mode_switch_allowed(enabled, modes["csp"], modes["pp"], standing=True)


def test_default_pdo_map():
    assert cia402.RPDO1.mapping_values() == [0x60400010, 0x60710010]
    assert cia402.TPDO1.mapping_values() == [0x60410010, 0x60640020]
    assert cia402.TPDO2.mapping_values() == [0x606C0020, 0x60770010]
    assert [p.cob_id(5) for p in (*cia402.RPDOS, *cia402.TPDOS)] == [0x205, 0x185, 0x285]
    assert [p.size_bytes for p in (*cia402.RPDOS, *cia402.TPDOS)] == [4, 6, 6]
    modes = cia402.OPERATION_MODES
    assert modes["cst"].rpdo1() == cia402.RPDO1
    csp = modes["csp"].rpdo1()
    assert csp.mapping_values() == [0x60400010, 0x607A0020] and csp.size_bytes == 6
    assert modes["csv"].rpdo1().mapping_values() == [0x60400010, 0x60FF0020]
    assert modes["hm"].rpdo1().mapping_values() == [0x60400010]
