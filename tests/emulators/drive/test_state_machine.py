"""Every transition of the CiA 402 chart, commanded by the master through the emulated drive.

The controlword goes out in RPDO1 and is latched on SYNC; the statusword comes back in TPDO1 and
is checked against canopen's ``State402`` masks (and again by SDO). Lockstep: deterministic."""

import pytest
from canopen.profiles.p402 import State402

from hil.protocols import cia402
from hil.protocols.cia402 import FAULT, FAULT_REACTION_ACTIVE, state_of
from hil.servo.config import load_drive_config
from hil.servo.rig import open_drive

SHUTDOWN, SWITCH_ON, ENABLE = cia402.CW_SHUTDOWN, cia402.CW_SWITCH_ON, cia402.CW_ENABLE_OPERATION
DISABLE_VOLTAGE, QUICK_STOP = cia402.CW_DISABLE_VOLTAGE, cia402.CW_QUICK_STOP
FAULT_RESET = cia402.CW_FAULT_RESET
SOD, RTSO, SO, OE, QSA = (cia402.SWITCH_ON_DISABLED, cia402.READY_TO_SWITCH_ON,
                          cia402.SWITCHED_ON, cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE)


def emulated_master(overrides=None):
    return open_drive("emulated", load_drive_config(overrides=overrides))


def assert_state(master, feedback, state):
    mask, value = State402.SW_MASK[state]
    assert feedback.fresh
    assert feedback.statusword & mask == value, (hex(feedback.statusword), state)
    assert state_of(feedback.statusword) == state
    assert state_of(master.sdo.read_int(0x6041, 0, "<H")) == state


# (controlword, state after the SYNC, CiA 402 transition)
CHART = [
    (DISABLE_VOLTAGE, SOD, 9),
    (SHUTDOWN, RTSO, 2),
    (SWITCH_ON, SO, 3),
    (ENABLE, OE, 4),
    (SWITCH_ON, SO, 5),          # disable operation
    (SHUTDOWN, RTSO, 6),
    (DISABLE_VOLTAGE, SOD, 7),
    (SHUTDOWN, RTSO, 2),
    (QUICK_STOP, SOD, 7),        # quick stop from READY TO SWITCH ON
    (SHUTDOWN, RTSO, 2),
    (SWITCH_ON, SO, 3),
    (DISABLE_VOLTAGE, SOD, 10),
    (SHUTDOWN, RTSO, 2),
    (SWITCH_ON, SO, 3),
    (QUICK_STOP, SOD, 10),       # quick stop from SWITCHED ON
    (SHUTDOWN, RTSO, 2),
    (ENABLE, OE, 3),             # switch on + enable operation: 3 then 4
    (SHUTDOWN, RTSO, 8),
    (SWITCH_ON, SO, 3),
    (ENABLE, OE, 4),
    (QUICK_STOP, QSA, 11),
    (QUICK_STOP, QSA, 11),       # held: stays
    (ENABLE, OE, 16),            # allowed with quick-stop option 5/6
    (QUICK_STOP, QSA, 11),
    (DISABLE_VOLTAGE, SOD, 12),
    (ENABLE, SOD, 0),            # no transition from SWITCH ON DISABLED on enable
    (FAULT_RESET | SHUTDOWN, SOD, 0),   # fault-reset bit outside FAULT: no command
]


def test_every_transition_of_the_chart_through_the_emulator():
    master = emulated_master({"master": {"quick_stop_option": 5}})
    master.start()
    for step, (controlword, state, transition) in enumerate(CHART):
        feedback = master.cycle(controlword)
        assert feedback.state == state, (step, transition, hex(controlword))
        assert_state(master, feedback, state)
    master.close()


def test_quick_stop_option_2_brakes_then_switches_off_by_itself():
    master = emulated_master()
    master.start()
    for _ in range(400):
        feedback = master.exchange(1000.0)
    assert feedback.velocity_deg_s > 500.0
    states = []
    for _ in range(2000):
        feedback = master.cycle(QUICK_STOP)
        states.append(feedback.state)
        if feedback.state == SOD:
            break
    assert states[0] == QSA and states[-1] == SOD  # transition 11, then 12 automatically
    assert abs(feedback.velocity_deg_s) < 2.0
    assert states.count(QSA) > 100  # it ramped for a while: braking at the limit from 560 deg/s
    master.close()


def test_quick_stop_option_0_switches_off_at_once():
    master = emulated_master({"master": {"quick_stop_option": 0}})
    master.start()
    for _ in range(100):
        master.exchange(500.0)
    feedback = master.cycle(QUICK_STOP)
    assert_state(master, feedback, SOD)
    assert feedback.current_ma == 0.0
    master.close()


def test_fault_reaction_then_fault_then_reset_by_the_rising_edge_of_bit_7():
    master = emulated_master({"master": {"current_limit_mA": 20000.0},
                              "emulator": {"overcurrent_trip_mA": 1500}})
    master.start()
    for _ in range(200):
        master.exchange(1000.0)
    states = [master.cycle(ENABLE, 2000).state]  # 2000 mA > trip: transition 13
    while states[-1] == FAULT_REACTION_ACTIVE and len(states) < 3000:
        states.append(master.cycle(ENABLE, 0).state)
    assert states[0] == FAULT_REACTION_ACTIVE and len(states) > 10  # braking from ~560 deg/s
    assert states[-1] == FAULT  # transition 14 at standstill
    assert_state(master, master.cycle(ENABLE), FAULT)  # enable does not leave FAULT
    assert_state(master, master.cycle(FAULT_RESET | ENABLE), SOD)  # bit 7 rises: transition 15
    assert_state(master, master.cycle(FAULT_RESET | ENABLE), SOD)  # held high: nothing more
    master.close()


def test_statusword_values_of_the_emulator_match_the_state402_masks():
    master = emulated_master()
    master.start()
    seen = {}
    for controlword in (DISABLE_VOLTAGE, SHUTDOWN, SWITCH_ON, ENABLE):
        feedback = master.cycle(controlword)
        seen[feedback.state] = feedback.statusword
    assert seen == {SOD: 0x0250, RTSO: 0x0231, SO: 0x0233, OE: 0x1237}
    for state, word in seen.items():
        matches = [s for s, (m, v) in State402.SW_MASK.items() if word & m == v]
        assert matches == [state]
    master.close()


@pytest.mark.parametrize("option", [1, 2])
def test_quick_stop_options_1_and_2_end_in_switch_on_disabled_at_standstill(option):
    master = emulated_master({"master": {"quick_stop_option": option}})
    master.start()
    assert_state(master, master.cycle(QUICK_STOP), SOD)  # at rest: the ramp ends at once
    master.close()
