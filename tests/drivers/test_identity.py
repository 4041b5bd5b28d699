"""A drive's identity (0x1018) and how hil tells its own emulator from a vendor's drive."""

from pathlib import Path

from hil.drivers.canopen.identity import Identity, not_hil_emulator, read_identity
from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.objects import ObjectStore
from hil.emulators.drive.od import build_object_dictionary
from hil.emulators.drive.twin import eds_twin
from hil.protocols.cia301 import SdoAbortError

DRIVES = Path(__file__).parents[1] / "data" / "drives"


class StoreReader:
    """An emulated dictionary's SDO reads, without a bus (the emulator's own checks)."""

    def __init__(self, store: ObjectStore) -> None:
        store.reset()
        self.store = store

    def read_int(self, index: int, subindex: int = 0, fmt: str = "<I",
                 timeout_s: float | None = None) -> int:
        return int.from_bytes(self.store.read(index, subindex), "little")


def test_hils_emulator_says_so_in_0x1018_5_with_its_own_dictionary_and_as_a_twin():
    own = read_identity(StoreReader(ObjectStore(build_object_dictionary(5))))
    assert own.hil_emulator and own.as_dict() == {"vendor_id": 0, "product_code": 0x402,
                                                  "revision": 1, "serial": 5}
    config = DriveEmulatorConfig(object_values=(((0x608F, 1), 4096), ((0x6075, 0), 2000),
                                                ((0x6073, 0), 3000)))
    twin = eds_twin(str(DRIVES / "nanotec" / "CL4-E-1-12.eds"), config)
    identity = read_identity(StoreReader(twin.store()))
    assert identity.hil_emulator and identity.vendor_id == 0x26C  # the vendor's identity


def test_a_drive_without_the_signature_is_a_vendors_drive():
    class Vendor:  # answers 0x1018:1..4 as a drive does, and aborts 0x1018:5
        def read_int(self, index: int, subindex: int = 0, fmt: str = "<I",
                     timeout_s: float | None = None) -> int:
            if subindex > 4:
                raise SdoAbortError(0x06090011)
            return (0, 0x402, 1, 7)[subindex - 1]

    assert not read_identity(Vendor()).hil_emulator  # hil's 0x1018:1..4 are no proof
    assert not Identity(0x00C0FFEE, 0x402).hil_emulator
    assert Identity(0xC0FFEE, None, 3).text() == "vendor 0xC0FFEE, revision 0x3"
    assert Identity().text() == "no identity"
    why = not_hil_emulator(3, Identity(0xC0FFEE, 17), "0x2005 time base")
    assert why.startswith("drive node 3 is not hil's drive emulator (0x1018: vendor 0xC0FFEE, "
                          "product 0x11): ") and "(0x2005 time base)" in why
