"""An ESI file as the emulated slave's SII: what it takes from the file, the one line for a
file that is not one, and SOEM reading the result from the slave's EEPROM."""

from __future__ import annotations

import pytest

from hil.emulators.ethercat.esi import sii_from_esi
from hil.emulators.ethercat.sii import build_sii
from hil.errors import HilError
from tests.ethercat_netns import soem_on, veth_pair

# the shape of a vendor's file (ETG.2000), written for this test: hex and decimal numbers, a
# namespace, mailboxes of 48 bytes where hil's are 128
ESI = """<?xml version="1.0" encoding="utf-8"?>
<EtherCATInfo xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" Version="1.6">
  <Vendor><Id>#x000000AB</Id><Name>Test Motion</Name></Vendor>
  <Descriptions>
    <Devices>
      <Device Physics="YY">
        <Type ProductCode="#x00001234" RevisionNo="65538">TM-402</Type>
        <Name LcId="1033"><![CDATA[TM-402 servo drive]]></Name>
        <Sm DefaultSize="48" StartAddress="#x1000" ControlByte="#x26" Enable="1">MBoxOut</Sm>
        <Sm DefaultSize="48" StartAddress="#x1030" ControlByte="#x22" Enable="1">MBoxIn</Sm>
        <Sm StartAddress="#x1060" ControlByte="#x64" Enable="1">Outputs</Sm>
        <Sm StartAddress="#x10F0" ControlByte="#x20" Enable="1">Inputs</Sm>
        <RxPdo Sm="2" Fixed="1"><Index>#x1600</Index><Name>Outputs</Name>
          <Entry><Index>#x6040</Index><SubIndex>0</SubIndex><BitLen>16</BitLen></Entry>
          <Entry><Index>#x607A</Index><SubIndex>0</SubIndex><BitLen>32</BitLen></Entry>
        </RxPdo>
        <TxPdo Sm="3" Fixed="1"><Index>#x1A00</Index><Name>Inputs</Name>
          <Entry><Index>#x6041</Index><SubIndex>0</SubIndex><BitLen>16</BitLen></Entry>
          <Entry><Index>#x6064</Index><SubIndex>0</SubIndex><BitLen>32</BitLen></Entry>
        </TxPdo>
        <Mailbox><CoE SdoInfo="1" PdoAssign="1" PdoConfig="1" CompleteAccess="1"/></Mailbox>
      </Device>
    </Devices>
  </Descriptions>
</EtherCATInfo>
"""


def test_the_sii_takes_identity_name_mailboxes_and_pdos_from_the_file(tmp_path):
    path = tmp_path / "tm402.xml"
    path.write_text(ESI)
    content = sii_from_esi(str(path))
    assert (content.vendor_id, content.product_code, content.revision) == (0xAB, 0x1234,
                                                                           65538)
    assert content.name == "TM-402 servo drive"
    assert [(sm.start, sm.length, sm.control, sm.use) for sm in content.sync_managers] == [
        (0x1000, 48, 0x26, 1), (0x1030, 48, 0x22, 2), (0x1060, 0, 0x64, 3),
        (0x10F0, 0, 0x20, 4)]
    assert [(pdo.index, [(e.index, e.bits) for e in pdo.entries]) for pdo in
            content.rx_pdos + content.tx_pdos] == [
        (0x1600, [(0x6040, 16), (0x607A, 32)]), (0x1A00, [(0x6041, 16), (0x6064, 32)])]
    assert content.coe_details == 0x0F  # SDO, info, assign, config: no complete access
    image = build_sii(content)
    assert image[0x10:0x14] == (0xAB).to_bytes(4, "little")
    assert image[0x30:0x38] == bytes.fromhex("0010 3000 3010 3000".replace(" ", ""))


@pytest.mark.parametrize(("text", "said"), [
    ("<Device/>", "the root element is <Device>, not <EtherCATInfo>"),
    ("<EtherCATInfo><Vendor><Id>#x2</Id></Vendor></EtherCATInfo>", "no <Vendor> or no"),
    (ESI.replace('ProductCode="#x00001234"', 'ProductCode="#xZZ"'),
     "ProductCode '#xZZ' is not a number"),
    ("not xml", "cannot read it"),
])
def test_a_file_that_is_no_esi_is_one_line_naming_why(tmp_path, text, said):
    path = tmp_path / "bad.xml"
    path.write_text(text)
    with pytest.raises(HilError) as refused:
        sii_from_esi(str(path))
    assert said in str(refused.value) and "\n" not in str(refused.value)


@pytest.mark.slow
def test_soem_reads_the_esis_identity_and_mailbox_from_the_slave(tmp_path):
    pytest.importorskip("pysoem", reason="the ethercat extra is not installed")

    path = tmp_path / "tm402.xml"
    path.write_text(ESI)
    with veth_pair() as veth, soem_on(veth, "--esi", str(path)) as master:
        assert master.config_init() == 1
        slave = master.slaves[0]
        assert (slave.man, slave.id, slave.rev, slave.name) == (
            0xAB, 0x1234, 65538, "TM-402 servo drive")
        # its 48-byte mailboxes where the ESI puts them: CoE through them
        statusword = int.from_bytes(slave.sdo_read(0x6041, 0), "little")
        assert statusword & 0x4F == 0x40  # SWITCH ON DISABLED
