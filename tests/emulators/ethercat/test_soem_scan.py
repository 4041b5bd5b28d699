"""hil's EtherCAT slave as SOEM sees it: a line of them (``hil emulate drive --ethercat``, a
process of its own) on one end of a veth pair in a namespace of the test's own, and SOEM
(pysoem, a master hil did not write) on the other: its scan (config_init: SII reads, station
addresses, mailbox), the PDO mapping it reads over CoE (config_map), the AL states up to OP,
process data with the working counter, and the AL status codes of a refused transition."""

from __future__ import annotations

import struct

import pytest

from tests.ethercat_netns import soem_on, veth_pair

pysoem = pytest.importorskip("pysoem", reason="the ethercat extra (pysoem) is not installed")

pytestmark = pytest.mark.slow

AL_STATUS, AL_CONTROL = 0x0130, 0x0120
SM2 = 0x0810


@pytest.fixture(scope="module")
def line():
    """Two emulated drives (nodes 1 and 2) in a line, and SOEM's master on the other end."""
    with veth_pair() as veth, soem_on(veth, "--node", "1", "--node", "2") as master:
        yield master


def test_soem_finds_each_slave_with_its_identity_from_the_sii(line):
    assert line.config_init() == 2
    for position, slave in enumerate(line.slaves):
        assert slave.name == "hil CiA 402 drive emulator"
        assert (slave.man, slave.id, slave.rev) == (0, 0x402, 1)  # the drive's 0x1018
        # the SII words SOEM read them from, read again one by one
        assert struct.unpack("<I", slave.eeprom_read(0x000A))[0] == 0x402
        assert struct.unpack("<HH", slave.eeprom_read(0x0018)) == (0x1000, 128)  # mailbox
        assert struct.unpack("<H", slave.eeprom_read(0x001C)[:2])[0] == 0x0004  # CoE
        # CoE: the drive's objects behind the mailbox, each slave its own drive
        assert struct.unpack("<I", slave.sdo_read(0x1018, 4))[0] == position + 1  # serial
        assert slave.sdo_read(0x1008, 0) == b"hil CiA 402 drive emulator"  # normal upload


def test_soem_maps_the_pdos_it_reads_over_coe_and_cycles_in_op(line):
    line.config_init()
    line.slaves[0].sdo_write(0x1C13, 0, bytes([1]))  # inputs: TxPDO 1 alone
    assert line.config_map() == 2 * 4 + 12 + 6  # RxPDO1 4 bytes; TxPDOs 12 / 6 bytes
    assert line.expected_wkc == 2 * 3          # LRW: 1 read + 2 write per slave
    assert line.state_check(pysoem.SAFEOP_STATE, 2_000_000) == pysoem.SAFEOP_STATE
    assert [len(s.input) for s in line.slaves] == [6, 12]
    line.state = pysoem.OP_STATE
    line.write_state()
    assert line.state_check(pysoem.OP_STATE, 2_000_000) == pysoem.OP_STATE
    for _ in range(20):
        line.send_processdata()
        assert line.receive_processdata(2_000_000) == line.expected_wkc
    statusword, _position = struct.unpack("<Hi", line.slaves[0].input)
    assert statusword & 0x4F == 0x40  # SWITCH ON DISABLED: the drive behind it answers
    # PDOs are set up in PRE-OP only, as on a vendor's drive: SOEM gets the abort's code
    with pytest.raises(pysoem.SdoError) as refused:
        line.slaves[0].sdo_write(0x1C12, 0, bytes([0]))
    assert refused.value.abort_code == 0x0800_0022
    assert line.slaves[0].sdo_read(0x1C12, 0) == bytes([1])


def test_a_transition_the_configuration_does_not_allow_is_refused_with_its_code(line):
    line.config_init()
    line.config_map()
    slave = line.slaves[1]
    slave.state = pysoem.PREOP_STATE
    slave.write_state()
    assert slave.state_check(pysoem.PREOP_STATE, 2_000_000) == pysoem.PREOP_STATE
    slave._fpwr(SM2 + 2, struct.pack("<H", 3))  # outputs SyncManager: 3 bytes, not 4
    slave._fpwr(AL_CONTROL, struct.pack("<H", pysoem.SAFEOP_STATE))
    status, _, code = struct.unpack("<HHH", slave._fprd(AL_STATUS, 6))
    assert (status, code) == (pysoem.PREOP_STATE | 0x10, 0x001D)  # invalid output config
    assert pysoem.al_status_code_to_string(code) == "Invalid output configuration"
    # the error holds until acknowledged; then a step too far is 0x0011
    slave._fpwr(AL_CONTROL, struct.pack("<H", pysoem.PREOP_STATE | 0x10))
    slave._fpwr(AL_CONTROL, struct.pack("<H", pysoem.OP_STATE))
    status, _, code = struct.unpack("<HHH", slave._fprd(AL_STATUS, 6))
    assert (status, code) == (pysoem.PREOP_STATE | 0x10, 0x0011)


def test_in_op_the_rxpdo_controlword_wins_over_one_written_by_sdo(line):
    """As on a vendor's drive with 0x6040 in its RxPDO: an SDO write of it is overwritten by
    the outputs before the drive's cycle reads it, so the state machine follows the RxPDO
    alone (a master enabling by SDO in OP stays in SWITCH ON DISABLED)."""
    line.config_init()
    line.config_map()
    assert line.state_check(pysoem.SAFEOP_STATE, 2_000_000) == pysoem.SAFEOP_STATE
    line.state = pysoem.OP_STATE
    line.write_state()
    assert line.state_check(pysoem.OP_STATE, 2_000_000) == pysoem.OP_STATE
    drive = line.slaves[0]

    def cycle(controlword: int) -> int:
        drive.output = struct.pack("<Hh", controlword, 0)
        line.send_processdata()
        assert line.receive_processdata(2_000_000) == line.expected_wkc
        return struct.unpack_from("<H", drive.input)[0] & 0x6F

    assert cycle(0x0000) == 0x40                            # SWITCH ON DISABLED
    drive.sdo_write(0x6040, 0, struct.pack("<H", 0x0006))    # shutdown, by SDO: taken...
    assert drive.sdo_read(0x6040, 0) == struct.pack("<H", 0x0006)
    assert struct.unpack("<H", drive.sdo_read(0x6041, 0))[0] & 0x6F == 0x40  # ...not applied
    assert cycle(0x0000) == 0x40                            # and the RxPDO's word wins
    assert drive.sdo_read(0x6040, 0) == struct.pack("<H", 0x0000)
    assert cycle(0x0006) == 0x21                            # READY TO SWITCH ON, by the RxPDO
    assert cycle(0x0000) == 0x40
