"""The SDO client (CiA 301 7.2.4): expedited and segmented upload, expedited download, and
downloads queued for the cyclic exchange.

A blocking request has one absolute deadline: frames that are not its answer (EMCY,
heartbeats, late TPDOs, garbage) go to ``other`` as they come and never extend it. A node that
has never answered is waited the SDO time-out, whatever longer bound lockstep gives a node
known to be there (``gone_after_s``); when it stays silent, the error names the nodes that
answer a scan of the bus (``census``: the master gives
:func:`hil.drivers.canopen.scan.discover`): a wrong node id is said at once, not after the
lockstep bound. A queued
download (:meth:`SdoClient.queue_write`) goes out with the next cycle's frames and its answer
is taken by the cyclic receive, so no SDO round trip runs inside a cycle; a refusal is kept
for :meth:`SdoClient.take_error`.
"""

from __future__ import annotations

import struct
import time
from collections import deque
from collections.abc import Callable
from typing import Protocol

from hil.drivers.canopen.errors import (
    DriveError,
    DriveGoneError,
    DriveLinkLostError,
    DriveNotFoundError,
)
from hil.drivers.canopen.link import Link
from hil.protocols.can_frames import Frame
from hil.protocols.cia301 import (
    SDO_ABORT,
    SDO_COMMAND_MASK,
    SDO_EXPEDITED,
    SDO_INITIATE_DOWNLOAD,
    SDO_INITIATE_UPLOAD,
    SDO_LAST_SEGMENT,
    SDO_REQUEST_BASE,
    SDO_RESPONSE_BASE,
    SDO_SIZE_INDICATED,
    SDO_TOGGLE,
    SDO_UPLOAD_SEGMENT,
    SdoAbortError,
)

_HEAD = struct.Struct("<BHB")
_SCS_UPLOAD_SEGMENT = 0x00
_SCS_INITIATE_UPLOAD = 0x40
_SCS_INITIATE_DOWNLOAD = 0x60
WAIT_SLICE_S = 0.05  # a blocking wait reads in slices this long (signals get through)


def download_request(index: int, subindex: int, value: int, fmt: str) -> bytes:
    """An expedited download of ``value`` packed with ``fmt`` (1 to 4 bytes)."""
    data = struct.pack(fmt, value)
    command = SDO_INITIATE_DOWNLOAD | SDO_EXPEDITED | SDO_SIZE_INDICATED | (4 - len(data)) << 2
    return _HEAD.pack(command, index, subindex) + data.ljust(4, b"\0")


def unpack_int(raw: bytes, fmt: str, what: str) -> int:
    """The value of an object uploaded as ``raw``, unpacked with ``fmt``; too short is a
    :class:`DriveError` naming ``what`` (the drive and object)."""
    size = struct.calcsize(fmt)
    if len(raw) < size:
        raise DriveError(f"{what} has {len(raw)} bytes, expected {size}")
    value: int = struct.unpack_from(fmt, raw)[0]
    return value


class SdoChannel(Protocol):
    """A drive's SDO as the CiA 402 modules use it (state, objects, profile, scaling, the
    settings journal), whatever carries it: :class:`SdoClient` on CAN, CoE over EtherCAT
    (:class:`hil.drivers.ethercat.coe.CoeSdo`). Refusals raise :class:`SdoAbortError` with the
    CiA 301 code; silence raises :class:`DriveLinkLostError` (or its kinds)."""

    node_id: int
    timeout_s: float

    def read(self, index: int, subindex: int = 0, timeout_s: float | None = None) -> bytes: ...

    def read_int(self, index: int, subindex: int = 0, fmt: str = "<I",
                 timeout_s: float | None = None) -> int: ...

    def write(self, index: int, subindex: int, value: int, fmt: str = "<I",
              timeout_s: float | None = None) -> None: ...

    def queue_write(self, index: int, subindex: int, value: int, fmt: str = "<I") -> None: ...

    def take_error(self) -> DriveError | SdoAbortError | None: ...


class SdoClient:
    """The SDO channel to node ``node_id`` over ``link``: each request waits ``timeout_s``;
    lockstep over a bus (``gone_after_s``): a node that has answered once is waited that
    long (wall clock) and is gone after it (:class:`DriveGoneError`). ``census``: the node
    ids that answer on the bus, asked when a node that never answered stays silent."""

    def __init__(self, link: Link, node_id: int, timeout_s: float,
                 other: Callable[[Frame], None], *, gone_after_s: float | None = None,
                 census: Callable[[], list[int]] | None = None) -> None:
        self.link, self.node_id, self.timeout_s = link, node_id, timeout_s
        self.gone_after_s = gone_after_s
        self._census_of = census
        self.answered = False  # the node has answered a request (it is on the bus)
        self._other = other
        self._request_id = SDO_REQUEST_BASE + node_id
        self.response_id = SDO_RESPONSE_BASE + node_id
        self._queued: deque[tuple[bytes, str]] = deque()
        self._outstanding: tuple[bytes, str] | None = None  # a queued download on the wire
        self._error: DriveError | SdoAbortError | None = None

    # -- blocking ---------------------------------------------------------------------------
    def read(self, index: int, subindex: int = 0, timeout_s: float | None = None) -> bytes:
        """Upload one object (expedited or segmented); its raw bytes."""
        what = f"read 0x{index:04X}:{subindex:02X}"
        response = self._request(_HEAD.pack(SDO_INITIATE_UPLOAD, index, subindex) + bytes(4),
                                 what, timeout_s)
        command = response[0]
        if command & SDO_COMMAND_MASK != _SCS_INITIATE_UPLOAD:
            raise DriveError(f"drive node {self.node_id}: bad SDO response to {what}")
        if command & SDO_EXPEDITED:
            size = 4 - ((command >> 2) & 0x3) if command & SDO_SIZE_INDICATED else 4
            return response[4:4 + size]
        data, toggle = bytearray(), 0
        while True:
            segment = self._request(bytes([SDO_UPLOAD_SEGMENT | toggle]) + bytes(7), what,
                                    timeout_s, segment=True)
            if segment[0] & SDO_COMMAND_MASK != _SCS_UPLOAD_SEGMENT or \
                    segment[0] & SDO_TOGGLE != toggle:
                raise DriveError(f"drive node {self.node_id}: bad SDO segment for {what}")
            data += segment[1:8 - ((segment[0] >> 1) & 0x7)]
            if segment[0] & SDO_LAST_SEGMENT:
                return bytes(data)
            toggle ^= SDO_TOGGLE

    def read_int(self, index: int, subindex: int = 0, fmt: str = "<I",
                 timeout_s: float | None = None) -> int:
        """Upload one object and unpack it with ``fmt``."""
        return unpack_int(self.read(index, subindex, timeout_s), fmt,
                          f"drive node {self.node_id}: 0x{index:04X}:{subindex:02X}")

    def write(self, index: int, subindex: int, value: int, fmt: str = "<I",
              timeout_s: float | None = None) -> None:
        """Expedited download of one value packed with ``fmt`` (1 to 4 bytes)."""
        self._request(download_request(index, subindex, value, fmt),
                      f"write 0x{index:04X}:{subindex:02X} = {value}", timeout_s)

    def _wait_s(self, timeout_s: float | None) -> float:
        """How long a request waits: as asked, else the SDO time-out, or for a node that has
        answered before, lockstep's longer bound."""
        if timeout_s is not None:
            return timeout_s
        if self.answered and self.gone_after_s is not None:
            return max(self.timeout_s, self.gone_after_s)
        return self.timeout_s

    def _silent(self, what: str, timeout_s: float) -> DriveLinkLostError:
        """The error of a request ``timeout_s`` unanswered: a node never heard from is not
        found (the nodes a scan of the bus finds named), one heard from is gone (lockstep) or
        its link lost."""
        message = (f"drive node {self.node_id} did not answer SDO {what} within "
                   f"{timeout_s:g} s on {self.link.name}")
        if not self.answered:
            return DriveNotFoundError(f"{message}: it has never answered{self._census()}")
        kind = DriveGoneError if self.gone_after_s is not None else DriveLinkLostError
        return kind(message)

    def _census(self) -> str:
        """Which nodes answer a scan of the bus (``census``), as the end of an error."""
        if self._census_of is None:
            return ""
        try:
            found = self._census_of()
        except DriveLinkLostError as exc:
            return f"; the bus could not be scanned ({exc})"
        if not found:
            return ("; no node answered a scan of the bus (is the drive powered, on this bus, "
                    "at its bit rate?)")
        names = ", ".join(str(node) for node in found)
        return (f"; the nodes that answered a scan of the bus: {names} (the drive's node id: "
                "--node N or [master] node_id)")

    def _request(self, request: bytes, what: str, timeout_s: float | None,
                 segment: bool = False) -> bytes:
        timeout_s = self._wait_s(timeout_s)
        self.link.send([(self._request_id, request)])
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise self._silent(what, timeout_s)
            frame = self.link.recv(min(remaining, WAIT_SLICE_S))
            if frame is None:
                continue
            can_id, response = frame
            if can_id != self.response_id or len(response) != 8:
                self._other(frame)
                continue
            if self._outstanding is not None and not segment and \
                    response[1:4] == self._outstanding[0][1:4] and \
                    response[1:4] != request[1:4]:
                self.on_response(response)  # a queued download's answer
                continue
            if segment or response[1:4] == request[1:4]:
                self.answered = True
                if response[0] == SDO_ABORT:
                    raise SdoAbortError(int.from_bytes(response[4:8], "little"),
                                        f"drive node {self.node_id} refused SDO {what}")
                return response

    # -- queued for the cyclic exchange -------------------------------------------------------
    def queue_write(self, index: int, subindex: int, value: int, fmt: str = "<I") -> None:
        """A download that goes out with the next cycle (one per cycle, in order)."""
        self._queued.append((download_request(index, subindex, value, fmt),
                             f"write 0x{index:04X}:{subindex:02X} = {value}"))

    def next_frames(self) -> list[Frame]:
        """The request to add to this cycle's frames (at most one on the wire at a time)."""
        if self._outstanding is not None or not self._queued:
            return []
        self._outstanding = self._queued.popleft()
        return [(self._request_id, self._outstanding[0])]

    def on_response(self, response: bytes) -> None:
        """An SDO answer the cyclic exchange received: the queued download's, or a stray."""
        outstanding = self._outstanding
        if outstanding is None or len(response) != 8 or response[1:4] != outstanding[0][1:4]:
            return
        self.answered = True
        self._outstanding = None
        if response[0] == SDO_ABORT:
            self._error = SdoAbortError(int.from_bytes(response[4:8], "little"),
                                        f"drive node {self.node_id} refused SDO {outstanding[1]}")
        elif response[0] & SDO_COMMAND_MASK != _SCS_INITIATE_DOWNLOAD:
            self._error = DriveError(f"drive node {self.node_id}: bad SDO response to "
                                     f"{outstanding[1]}")

    def take_error(self) -> DriveError | SdoAbortError | None:
        """The refusal of a queued download, once."""
        error, self._error = self._error, None
        return error

    @property
    def idle(self) -> bool:
        """No queued download waiting or on the wire."""
        return self._outstanding is None and not self._queued
