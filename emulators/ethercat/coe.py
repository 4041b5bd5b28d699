"""CANopen over EtherCAT in the slave's mailbox (ETG.1000.6 5.6): the SDO server (expedited,
normal and segmented upload; expedited, normal and segmented download; aborts with the CiA 301
code) and emergencies. It knows no object dictionary: ``upload(index, subindex) -> bytes`` and
``download(index, subindex, data)`` raise :class:`~hil.protocols.cia301.SdoAbortError`.

Complete access (whole objects at once) is refused with an abort: the SII does not claim it
(:data:`~hil.protocols.ethercat.COE_COMPLETE_ACCESS`), so a master does not ask for it.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from hil.protocols.cia301 import ABORT_COMMAND, ABORT_GENERAL, ABORT_TOGGLE, SdoAbortError
from hil.protocols.ethercat import (
    COE_EMERGENCY,
    COE_HEADER,
    COE_SDO_REQUEST,
    COE_SDO_RESPONSE,
    EMERGENCY,
    MAILBOX_ERROR_UNSUPPORTED_PROTOCOL,
    MAILBOX_HEADER,
    MAILBOX_TYPE_COE,
    MAILBOX_TYPE_ERROR,
    SDO_HEADER,
)

# the client's command specifiers (bits 7-5) and the server's answers
CCS_DOWNLOAD_SEGMENT, CCS_INITIATE_DOWNLOAD, CCS_INITIATE_UPLOAD, CCS_UPLOAD_SEGMENT = 0, 1, 2, 3
SCS_UPLOAD_SEGMENT, SCS_DOWNLOAD_SEGMENT, SCS_INITIATE_UPLOAD, SCS_INITIATE_DOWNLOAD = \
    0x00, 0x20, 0x40, 0x60
SDO_ABORT = 0x80
EXPEDITED, SIZE_INDICATED, COMPLETE_ACCESS, TOGGLE, LAST_SEGMENT = 0x02, 0x01, 0x10, 0x10, 0x01
HEADERS = MAILBOX_HEADER.size + COE_HEADER.size   # 8 bytes before the SDO's own
SEGMENT_HEADER = 1                                 # an SDO segment: one command byte


def mailbox_message(kind: int, payload: bytes, counter: int = 0) -> bytes:
    """A mailbox message: its header (length, address 0, priority 0, type and counter)."""
    return MAILBOX_HEADER.pack(len(payload), 0, 0, kind | (counter & 0x7) << 4) + payload


def coe(service: int, payload: bytes) -> bytes:
    return mailbox_message(MAILBOX_TYPE_COE, COE_HEADER.pack(service << 12) + payload)


def emergency(code: int, register: int, data: bytes = b"") -> bytes:
    """A CoE emergency, as a CAN EMCY's eight bytes."""
    return coe(COE_EMERGENCY, EMERGENCY.pack(code, register, data.ljust(5, b"\0")[:5]))


class CoeServer:
    """The SDO server of one slave's mailbox (``size``: the mailbox's bytes)."""

    def __init__(self, upload: Callable[[int, int], bytes],
                 download: Callable[[int, int, bytes], None], size: int) -> None:
        self._upload, self._download = upload, download
        self.size = size
        self._upload_left: tuple[int, int, bytes, int] | None = None   # index, sub, rest, toggle
        self._download_at: tuple[int, int, bytearray, int, int] | None = None  # +size, toggle

    def handle(self, message: bytes) -> list[bytes]:
        """One mailbox message from the master; the answers to queue."""
        if len(message) < MAILBOX_HEADER.size:
            return []
        length, _, _, kind = MAILBOX_HEADER.unpack_from(message)
        body = message[MAILBOX_HEADER.size:MAILBOX_HEADER.size + length]
        if kind & 0x0F != MAILBOX_TYPE_COE:
            return [mailbox_message(MAILBOX_TYPE_ERROR,
                                    struct.pack("<HH", 1, MAILBOX_ERROR_UNSUPPORTED_PROTOCOL))]
        if len(body) < COE_HEADER.size + SDO_HEADER.size or \
                COE_HEADER.unpack_from(body)[0] >> 12 != COE_SDO_REQUEST:
            return []
        sdo = body[COE_HEADER.size:]
        command, index, subindex = SDO_HEADER.unpack_from(sdo)
        try:
            return [coe(COE_SDO_RESPONSE, self._serve(command, index, subindex, sdo))]
        except SdoAbortError as exc:  # ETG.1000.6: an "abort SDO transfer request"
            self._upload_left = self._download_at = None
            return [coe(COE_SDO_REQUEST, SDO_HEADER.pack(SDO_ABORT, index, subindex)
                        + struct.pack("<I", exc.code))]

    def _serve(self, command: int, index: int, subindex: int, sdo: bytes) -> bytes:
        specifier = command >> 5
        if command & COMPLETE_ACCESS and specifier in (CCS_INITIATE_UPLOAD,
                                                      CCS_INITIATE_DOWNLOAD):
            raise SdoAbortError(ABORT_COMMAND)
        if specifier == CCS_INITIATE_UPLOAD:
            return self._initiate_upload(index, subindex)
        if specifier == CCS_UPLOAD_SEGMENT:
            return self._upload_segment(command)
        if specifier == CCS_INITIATE_DOWNLOAD:
            return self._initiate_download(command, index, subindex, sdo)
        if specifier == CCS_DOWNLOAD_SEGMENT:
            return self._download_segment(command, sdo)
        raise SdoAbortError(ABORT_COMMAND)

    def _initiate_upload(self, index: int, subindex: int) -> bytes:
        self._upload_left = None
        data = self._upload(index, subindex)
        if len(data) <= 4:
            return SDO_HEADER.pack(SCS_INITIATE_UPLOAD | EXPEDITED | SIZE_INDICATED
                                   | (4 - len(data)) << 2, index, subindex) + data.ljust(4, b"\0")
        room = self.size - HEADERS - SDO_HEADER.size - 4
        first, rest = data[:room], data[room:]
        if rest:
            self._upload_left = (index, subindex, rest, 0)
        return SDO_HEADER.pack(SCS_INITIATE_UPLOAD | SIZE_INDICATED, index, subindex) + \
            struct.pack("<I", len(data)) + first

    def _upload_segment(self, command: int) -> bytes:
        if self._upload_left is None:
            raise SdoAbortError(ABORT_COMMAND)
        index, subindex, rest, toggle = self._upload_left
        if command & TOGGLE != toggle:
            raise SdoAbortError(ABORT_TOGGLE)
        room = self.size - HEADERS - SEGMENT_HEADER
        chunk, rest = rest[:room], rest[room:]
        self._upload_left = (index, subindex, rest, toggle ^ TOGGLE) if rest else None
        seven = max(0, 7 - len(chunk))  # bytes of a short segment that are not data
        return bytes([SCS_UPLOAD_SEGMENT | toggle | seven << 1
                      | (0 if rest else LAST_SEGMENT)]) + chunk

    def _initiate_download(self, command: int, index: int, subindex: int, sdo: bytes) -> bytes:
        self._download_at = None
        if command & EXPEDITED:
            size = 4 - (command >> 2 & 0x3) if command & SIZE_INDICATED else 4
            self._download(index, subindex, sdo[4:4 + size])
        else:
            (size,) = struct.unpack_from("<I", sdo, 4)
            data = sdo[8:8 + size]
            if len(data) < size:  # the rest comes in segments
                self._download_at = (index, subindex, bytearray(data), size, 0)
            else:
                self._download(index, subindex, data)
        return SDO_HEADER.pack(SCS_INITIATE_DOWNLOAD, index, subindex) + bytes(4)

    def _download_segment(self, command: int, sdo: bytes) -> bytes:
        if self._download_at is None:
            raise SdoAbortError(ABORT_COMMAND)
        index, subindex, data, size, toggle = self._download_at
        if command & TOGGLE != toggle:
            raise SdoAbortError(ABORT_TOGGLE)
        data += sdo[1:1 + size - len(data)]
        if command & LAST_SEGMENT or len(data) >= size:
            self._download_at = None
            if len(data) != size:
                raise SdoAbortError(ABORT_GENERAL)
            self._download(index, subindex, bytes(data))
        else:
            self._download_at = (index, subindex, data, size, toggle ^ TOGGLE)
        return bytes([SCS_DOWNLOAD_SEGMENT | toggle]) + bytes(7)
