"""CoE over the mailbox (ETG.1000.6 5.6): the SDO client of one EtherCAT slave, an
:class:`~hil.drivers.canopen.sdo.SdoChannel` like the CAN :class:`SdoClient`: expedited and
normal upload and download, segmented upload, aborts as :class:`SdoAbortError` with their
CiA 301 code, and the slave's CoE emergencies, handed on as the eight bytes of a CAN EMCY.

The mailbox is two SyncManagers in the slave's memory (their place and size from its SII): a
request is written into SM0's area in one datagram; the answer is read from SM1's area once its
status says it is full. Each is a FPWR / FPRD through SOEM (its ``_fpwr`` / ``_fprd``). A
download queued for the cyclic exchange (:meth:`CoeSdo.queue_write`) goes out before the next
cycle; its refusal is kept for :meth:`CoeSdo.take_error`.
"""

from __future__ import annotations

import struct
import time
from collections import deque
from collections.abc import Callable

from hil.drivers.canopen.errors import DriveError, DriveLinkLostError
from hil.drivers.canopen.sdo import unpack_int
from hil.drivers.ethercat.segment import Segment
from hil.protocols.cia301 import SDO_COMMAND_MASK, SdoAbortError
from hil.protocols.ethercat import (
    COE_EMERGENCY,
    COE_HEADER,
    COE_SDO_REQUEST,
    COE_SDO_RESPONSE,
    MAILBOX_HEADER,
    MAILBOX_TYPE_COE,
    REG_SM0,
    SDO_HEADER,
    SM_SIZE,
    SM_STATUS_MAILBOX_FULL,
)

SM_STATUS = 5  # the status byte of a SyncManager's registers
UPLOAD, DOWNLOAD_EXPEDITED, DOWNLOAD_NORMAL, UPLOAD_SEGMENT = 0x40, 0x23, 0x21, 0x60
ABORT, EXPEDITED, SIZE_INDICATED, TOGGLE, LAST = 0x80, 0x02, 0x01, 0x10, 0x01
DOWNLOAD_CONFIRMED = 0x60  # the initiate-download response's command specifier
POLL_S = 50e-6   # the answer's mailbox polled this often


def download_confirmed(command: int) -> bool:
    """Whether an answer's command byte confirms a download: its specifier (the top three
    bits) is 3, whatever the bits CiA 301 reserves hold (some slaves echo the request's size
    bits there: 0x6B for a 1-byte expedited download), as the CAN SDO client takes it."""
    return command & SDO_COMMAND_MASK == DOWNLOAD_CONFIRMED


class CoeSdo:
    """The SDO channel to EtherCAT slave ``position`` on ``segment`` (``node_id``: the drive's
    name in messages). ``on_emergency(data)``: each CoE emergency, as a CAN EMCY's bytes."""

    def __init__(self, segment: Segment, position: int, node_id: int, timeout_s: float,
                 on_emergency: Callable[[bytes], None]) -> None:
        self.segment, self.position, self.node_id = segment, position, node_id
        self.timeout_s = timeout_s
        self.on_emergency = on_emergency
        self.answered = False
        self._counter = 0
        self._queued: deque[tuple[int, int, int, str]] = deque()
        self._error: DriveError | SdoAbortError | None = None

    # -- SdoChannel ---------------------------------------------------------------------------
    def read(self, index: int, subindex: int = 0, timeout_s: float | None = None) -> bytes:
        what = f"read 0x{index:04X}:{subindex:02X}"
        answer = self._request(SDO_HEADER.pack(UPLOAD, index, subindex) + bytes(4), index,
                               subindex, what, timeout_s)
        command = answer[0]
        if command & 0xE0 != 0x40:
            raise DriveError(f"drive {self._name}: bad SDO answer to {what}")
        if command & EXPEDITED:
            size = 4 - (command >> 2 & 0x3) if command & SIZE_INDICATED else 4
            return answer[4:4 + size]
        (size,) = struct.unpack_from("<I", answer, 4)
        data, toggle = bytearray(answer[8:8 + size]), 0
        while len(data) < size:
            segment = self._request(bytes([UPLOAD_SEGMENT | toggle]) + bytes(7), index,
                                    subindex, what, timeout_s, segment=True)
            if segment[0] & 0xE0 or segment[0] & TOGGLE != toggle:
                raise DriveError(f"drive {self._name}: bad SDO segment for {what}")
            data += segment[1:1 + size - len(data)]
            if segment[0] & LAST:
                break
            toggle ^= TOGGLE
        return bytes(data)

    def read_int(self, index: int, subindex: int = 0, fmt: str = "<I",
                 timeout_s: float | None = None) -> int:
        return unpack_int(self.read(index, subindex, timeout_s), fmt,
                          f"drive {self._name}: 0x{index:04X}:{subindex:02X}")

    def write(self, index: int, subindex: int, value: int, fmt: str = "<I",
              timeout_s: float | None = None) -> None:
        self.download(index, subindex, struct.pack(fmt, value), timeout_s,
                      f"write 0x{index:04X}:{subindex:02X} = {value}")

    def download(self, index: int, subindex: int, data: bytes, timeout_s: float | None = None,
                 what: str | None = None) -> None:
        """Any number of bytes (expedited up to four, else normal in one mailbox)."""
        what = what or f"write 0x{index:04X}:{subindex:02X}"
        if len(data) <= 4:
            request = SDO_HEADER.pack(DOWNLOAD_EXPEDITED | (4 - len(data)) << 2, index,
                                      subindex) + data.ljust(4, b"\0")
        else:
            room = self.segment.mailbox(self.position)[1] - MAILBOX_HEADER.size - \
                COE_HEADER.size - SDO_HEADER.size - 4
            if len(data) > room:
                raise DriveError(f"drive {self._name}: {what}: {len(data)} bytes do not fit "
                                 f"its mailbox ({room} bytes)")
            request = SDO_HEADER.pack(DOWNLOAD_NORMAL, index, subindex) + \
                struct.pack("<I", len(data)) + data
        answer = self._request(request, index, subindex, what, timeout_s)
        if not download_confirmed(answer[0]):
            raise DriveError(f"drive {self._name}: bad SDO answer to {what}")

    def queue_write(self, index: int, subindex: int, value: int, fmt: str = "<I") -> None:
        """A download that goes out before the next cycle."""
        self._queued.append((index, subindex, value, fmt))

    def flush(self) -> None:
        """The queued downloads, now (before a cycle); a refusal kept for take_error."""
        while self._queued:
            index, subindex, value, fmt = self._queued.popleft()
            try:
                self.write(index, subindex, value, fmt)
            except (SdoAbortError, DriveError) as exc:
                self._error = exc

    def take_error(self) -> DriveError | SdoAbortError | None:
        error, self._error = self._error, None
        return error

    # -- the mailbox ------------------------------------------------------------------------------
    @property
    def _name(self) -> str:
        return f"node {self.node_id} (EtherCAT slave {self.position} on {self.segment.name})"

    def _request(self, sdo: bytes, index: int, subindex: int, what: str,
                 timeout_s: float | None, segment: bool = False) -> bytes:
        """Send one CoE SDO request; its answer's SDO bytes (an abort raised)."""
        wait_s = self.timeout_s if timeout_s is None else timeout_s
        self.poll()  # what the slave said before (an emergency) is not this answer
        self._send(COE_HEADER.pack(COE_SDO_REQUEST << 12) + sdo)
        deadline = time.monotonic() + wait_s
        while True:
            body = self._receive(deadline)
            if body is None:
                raise DriveLinkLostError(f"drive {self._name} did not answer SDO {what} within "
                                         f"{wait_s:g} s")
            service = COE_HEADER.unpack_from(body)[0] >> 12
            if service == COE_EMERGENCY:
                self.on_emergency(body[2:10])
                continue
            answer = body[COE_HEADER.size:]
            # an abort is an "abort SDO transfer request" (service 2, ETG.1000.6); some
            # slaves send it as a response: either is taken
            aborted = len(answer) >= 8 and answer[0] == ABORT and \
                service in (COE_SDO_REQUEST, COE_SDO_RESPONSE)
            if not aborted and (service != COE_SDO_RESPONSE or len(answer) < 8):
                continue
            if not segment and struct.unpack_from("<HB", answer, 1) != (index, subindex):
                continue  # an answer to another request
            self.answered = True
            if answer[0] == ABORT:
                raise SdoAbortError(struct.unpack_from("<I", answer, 4)[0],
                                    f"drive {self._name} refused SDO {what}")
            return answer

    def poll(self, wait_s: float | None = None) -> None:
        """Read what waits in the slave's mailbox (its emergencies) without waiting for more;
        ``wait_s``: how long each read may take (None: the SDO's own bound)."""
        while (body := self._receive(None, wait_s)) is not None:
            if COE_HEADER.unpack_from(body)[0] >> 12 == COE_EMERGENCY:
                self.on_emergency(body[2:10])

    def _send(self, body: bytes) -> None:
        start, size, _, _ = self.segment.mailbox(self.position)
        self._counter = self._counter % 7 + 1
        message = MAILBOX_HEADER.pack(len(body), 0, 0, MAILBOX_TYPE_COE | self._counter << 4) \
            + body
        self.segment.fpwr(self.position, start, message.ljust(size, b"\0"))

    def _receive(self, deadline: float | None, wait_s: float | None = None) -> bytes | None:
        """The CoE body of the next message in the slave's mailbox (None: none came by
        ``deadline``; with no deadline, none there now); each read waited ``wait_s`` for."""
        _, _, start, size = self.segment.mailbox(self.position)
        status_at = REG_SM0 + SM_SIZE + SM_STATUS
        wait_us = round((self.timeout_s if wait_s is None else wait_s) * 1e6)
        while True:
            if self.segment.fprd(self.position, status_at, 1, wait_us)[0] & \
                    SM_STATUS_MAILBOX_FULL:
                message = self.segment.fprd(self.position, start, size, wait_us)
                length, _, _, kind = MAILBOX_HEADER.unpack_from(message)
                body = message[MAILBOX_HEADER.size:MAILBOX_HEADER.size + length]
                if kind & 0x0F == MAILBOX_TYPE_COE and len(body) >= COE_HEADER.size:
                    return body
                continue  # another protocol's (a mailbox error): not ours
            if deadline is None or time.monotonic() >= deadline:
                return None
            time.sleep(POLL_S)
