"""The emulated drive's SDO server (CiA 301 7.2.4): expedited and segmented upload and
download, and aborts. Block transfers are answered with an abort (command specifier not
valid), as CiA 301 allows a server that does not support them.

The server knows no object dictionary: it calls ``read(index, subindex) -> bytes`` and
``write(index, subindex, data)``, which raise :class:`SdoAbortError` with the CiA 301 abort code,
and hands each answer frame's 8 bytes to ``respond``.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from hil.protocols.cia301 import (
    ABORT_COMMAND,
    ABORT_GENERAL,
    ABORT_TOGGLE,
    SDO_ABORT,
    SDO_COMMAND_MASK,
    SDO_DOWNLOAD_SEGMENT,
    SDO_EXPEDITED,
    SDO_INITIATE_DOWNLOAD,
    SDO_INITIATE_UPLOAD,
    SDO_LAST_SEGMENT,
    SDO_SIZE_INDICATED,
    SDO_TOGGLE,
    SDO_UPLOAD_SEGMENT,
    SdoAbortError,
)

_HEAD = struct.Struct("<BHB")  # command, index, sub-index
# the server's answers (CiA 301: scs); for an upload segment the specifier is 0
_SCS_UPLOAD_SEGMENT = 0x00
_SCS_DOWNLOAD_SEGMENT = 0x20
_SCS_INITIATE_UPLOAD = 0x40
_SCS_INITIATE_DOWNLOAD = 0x60



class SdoServer:
    """One SDO server channel; :meth:`handle` takes each request frame's data in order."""

    def __init__(self, read: Callable[[int, int], bytes],
                 write: Callable[[int, int, bytes], None],
                 respond: Callable[[bytes], None]) -> None:
        self._read, self._write, self._respond = read, write, respond
        self._index = self._subindex = 0  # of the transfer in progress (or the last one)
        self._upload: bytearray | None = None    # what a segmented upload has still to send
        self._download: bytearray | None = None  # what a segmented download has received
        self._toggle = 0

    def handle(self, data: bytes) -> None:
        """One request from the client; the answer (or an abort) goes to ``respond``."""
        if len(data) != 8:  # SDO frames are always 8 bytes
            if len(data) >= 4:
                _, self._index, self._subindex = _HEAD.unpack_from(data)
            self.abort(ABORT_COMMAND)
            return
        command = data[0]
        specifier = command & SDO_COMMAND_MASK
        try:
            if specifier == SDO_INITIATE_UPLOAD:
                self._initiate_upload(data)
            elif specifier == SDO_UPLOAD_SEGMENT:
                self._upload_segment(command)
            elif specifier == SDO_INITIATE_DOWNLOAD:
                self._initiate_download(data)
            elif specifier == SDO_DOWNLOAD_SEGMENT:
                self._download_segment(command, data)
            elif specifier == SDO_ABORT:  # the client gave up: forget the transfer
                self._upload = self._download = None
            else:  # block transfers, unknown specifiers
                _, self._index, self._subindex = _HEAD.unpack_from(data)
                raise SdoAbortError(ABORT_COMMAND)
        except SdoAbortError as exc:
            self.abort(exc.code)

    def abort(self, code: int = ABORT_GENERAL) -> None:
        """Abort the transfer of the current object with ``code``."""
        self._upload = self._download = None
        self._respond(struct.pack("<BHBL", SDO_ABORT, self._index, self._subindex, code))

    def _answer(self, command: int, payload: bytes = b"") -> None:
        self._respond(_HEAD.pack(command, self._index, self._subindex) + payload.ljust(4, b"\0"))

    def _initiate_upload(self, request: bytes) -> None:
        _, self._index, self._subindex = _HEAD.unpack_from(request)
        self._upload = self._download = None
        data = self._read(self._index, self._subindex)
        if len(data) <= 4:
            self._answer(_SCS_INITIATE_UPLOAD | SDO_EXPEDITED | SDO_SIZE_INDICATED
                         | (4 - len(data)) << 2, data)
            return
        self._upload, self._toggle = bytearray(data), 0
        self._answer(_SCS_INITIATE_UPLOAD | SDO_SIZE_INDICATED, struct.pack("<L", len(data)))

    def _upload_segment(self, command: int) -> None:
        if self._upload is None:
            raise SdoAbortError(ABORT_COMMAND)  # a segment without an upload in progress
        if command & SDO_TOGGLE != self._toggle:
            raise SdoAbortError(ABORT_TOGGLE)
        chunk = bytes(self._upload[:7])
        del self._upload[:7]
        last = not self._upload
        self._respond(bytes([_SCS_UPLOAD_SEGMENT | self._toggle | (7 - len(chunk)) << 1
                             | (SDO_LAST_SEGMENT if last else 0)]) + chunk.ljust(7, b"\0"))
        self._toggle ^= SDO_TOGGLE
        if last:
            self._upload = None

    def _initiate_download(self, request: bytes) -> None:
        command, self._index, self._subindex = _HEAD.unpack_from(request)
        self._upload = self._download = None
        if command & SDO_EXPEDITED:
            size = 4 - ((command >> 2) & 0x3) if command & SDO_SIZE_INDICATED else 4
            self._write(self._index, self._subindex, bytes(request[4:4 + size]))
        else:
            self._download, self._toggle = bytearray(), 0
        self._answer(_SCS_INITIATE_DOWNLOAD)

    def _download_segment(self, command: int, request: bytes) -> None:
        if self._download is None:
            raise SdoAbortError(ABORT_COMMAND)  # a segment without a download in progress
        if command & SDO_TOGGLE != self._toggle:
            raise SdoAbortError(ABORT_TOGGLE)
        self._download += request[1:8 - ((command >> 1) & 0x7)]
        toggle = self._toggle
        self._toggle ^= SDO_TOGGLE
        if command & SDO_LAST_SEGMENT:
            data, self._download = bytes(self._download), None
            self._write(self._index, self._subindex, data)
        self._respond(bytes([_SCS_DOWNLOAD_SEGMENT | toggle]) + bytes(7))
