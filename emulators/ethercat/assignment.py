"""Which PDOs an emulated slave's process data carries: 0x1C12 (the outputs, SyncManager 2:
RxPDOs 0x1600..) and 0x1C13 (the inputs, SyncManager 3: TxPDOs 0x1A00..), written in PRE-OP
in ETG.1020's order (sub-index 0 cleared, then the PDOs, then their count).

The PDOs each can carry and their rules are the SII's (:class:`~hil.emulators.ethercat.sii.
PdoSpec`: hil's defaults, or a vendor's ``<RxPdo>`` / ``<TxPdo>``): a count that assigns two
PDOs one ``excludes`` is refused (0x06090030), as is a PDO of the other direction or one the
drive does not have; a ``mandatory`` PDO left out keeps the slave out of SAFE-OP (AL status
0x001D outputs, 0x001E inputs). The power-on assignment is the dictionary's 0x1C12 / 0x1C13
where it has a value (an ESI's DefaultData), else the PDOs the SII gives a SyncManager; the
dictionary's number of sub-indices is how many PDOs it holds (else :data:`ASSIGN_SLOTS`)."""

from __future__ import annotations

import struct
from collections.abc import Container, Mapping

from hil.emulators.ethercat.sii import PdoSpec
from hil.protocols.cia301 import (
    ABORT_NO_SUBINDEX,
    ABORT_UNSUPPORTED,
    ABORT_VALUE,
    SdoAbortError,
)
from hil.protocols.ethercat import (
    AL_INVALID_INPUT_CONFIG,
    AL_INVALID_OUTPUT_CONFIG,
    RXPDO_ASSIGN,
    RXPDO_MAPPINGS,
    TXPDO_ASSIGN,
    TXPDO_MAPPINGS,
)

ASSIGN_SLOTS = 4  # PDOs an assignment object holds, where the dictionary does not say
SYNC_MANAGERS = {RXPDO_ASSIGN: 2, TXPDO_ASSIGN: 3}
MAPPINGS = {RXPDO_ASSIGN: RXPDO_MAPPINGS, TXPDO_ASSIGN: TXPDO_MAPPINGS}
REFUSALS = {RXPDO_ASSIGN: AL_INVALID_OUTPUT_CONFIG, TXPDO_ASSIGN: AL_INVALID_INPUT_CONFIG}


class Assignment:
    """One assignment object (``index``: 0x1C12 or 0x1C13) over the drive's PDO mapping
    objects ``pdos``, with the rules of ``specs`` (the SII's PDOs of its direction)."""

    def __init__(self, index: int, specs: tuple[PdoSpec, ...], pdos: Container[int],
                 values: Mapping[tuple[int, int], object]) -> None:
        self.index = index
        self.pdos = pdos
        self.excludes = {spec.index: set(spec.excludes) for spec in specs}
        self.mandatory = tuple(spec.index for spec in specs if spec.mandatory)
        subs = sorted(sub for index_, sub in values if index_ == index and sub)
        self.size = len(subs) or ASSIGN_SLOTS
        given = values.get((index, 0))
        if isinstance(given, int):  # the dictionary's power-on value
            power_on = [values.get((index, sub)) for sub in range(1, min(given, self.size) + 1)]
        else:
            power_on = [spec.index for spec in specs
                        if spec.assigned and spec.sync_manager == SYNC_MANAGERS[index]]
        self.assigned = [pdo for pdo in power_on if isinstance(pdo, int) and pdo in pdos]
        # what each sub-index holds (sub-index 0, the count, says how many are assigned)
        self.slots = (self.assigned + [0] * self.size)[:self.size]

    def read(self, subindex: int) -> bytes:
        if subindex > self.size:
            raise SdoAbortError(ABORT_NO_SUBINDEX)
        if subindex == 0:
            return bytes([len(self.assigned)])
        return struct.pack("<H", self.slots[subindex - 1])

    def write(self, subindex: int, value: int) -> None:
        """Sub-index 0 the count (0 first, then the PDOs, then the count)."""
        if subindex > self.size:
            raise SdoAbortError(ABORT_NO_SUBINDEX)
        if subindex == 0:
            chosen = self.slots[:value]
            if value > self.size or not all(chosen) or self._excluded(chosen):
                raise SdoAbortError(ABORT_VALUE)
            self.assigned = chosen
            return
        if self.assigned:
            raise SdoAbortError(ABORT_UNSUPPORTED)  # clear the count first
        if value not in MAPPINGS[self.index] or value not in self.pdos:
            raise SdoAbortError(ABORT_VALUE)
        self.slots[subindex - 1] = value

    def _excluded(self, chosen: list[int]) -> bool:
        """Whether ``chosen`` holds two PDOs one of which excludes the other."""
        return any(other in self.excludes.get(pdo, ()) for pdo in chosen for other in chosen)

    def refusal(self) -> int:
        """The AL status code keeping the slave out of SAFE-OP (0: none): a mandatory PDO
        is not assigned."""
        missing = any(pdo not in self.assigned for pdo in self.mandatory)
        return REFUSALS[self.index] if missing else 0
