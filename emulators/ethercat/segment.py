"""A line of emulated EtherCAT slaves on one network interface (a veth end): every EtherCAT
frame that arrives is passed through each slave in order, as the frame travels down the line,
and sent back out of the interface, as the last slave's port 0 returns it (its source address
marked locally administered, as an ESC does).

A raw ``AF_PACKET`` socket bound to EtherType 0x88A4 (CAP_NET_RAW): it sees only EtherCAT
frames that arrive, never the ones it sends. Between frames, at least every
:data:`SERVICE_PERIOD_S`, each drive's timers run (its watchdogs; in lockstep the master's
cycles are its time, and a master gone silent for longer than it said is a SYNC loss).
"""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Sequence
from typing import Protocol

from hil.emulators.ethercat.slave import EthercatDrive
from hil.protocols.ethercat import (
    AUTO_INCREMENT,
    BROADCAST,
    DATAGRAM_HEADER,
    ECAT_HEADER,
    ECAT_TYPE_COMMANDS,
    ETH_HEADER,
    ETHERTYPE,
    LENGTH_MASK,
    MORE,
    WKC,
)

SERVICE_PERIOD_S = 0.001
FRAME_MAX = 1518
LOCALLY_ADMINISTERED = 0x02


def pass_frame(slaves: Sequence[EthercatDrive], frame: bytearray) -> bool:
    """Pass one frame through ``slaves`` in place; whether it was an EtherCAT command frame
    (one to send back)."""
    if len(frame) < ETH_HEADER + ECAT_HEADER.size or \
            struct.unpack_from("!H", frame, 12)[0] != ETHERTYPE:
        return False
    (header,) = ECAT_HEADER.unpack_from(frame, ETH_HEADER)
    if header >> 12 != ECAT_TYPE_COMMANDS:
        return False
    view = memoryview(frame)
    offset = ETH_HEADER + ECAT_HEADER.size
    while offset + DATAGRAM_HEADER.size + WKC.size <= len(frame):
        command, _, adp, ado, flags, _ = DATAGRAM_HEADER.unpack_from(frame, offset)
        start = offset + DATAGRAM_HEADER.size
        end = start + (flags & LENGTH_MASK)
        if end + WKC.size > len(frame):
            break
        (wkc,) = WKC.unpack_from(frame, end)
        data = view[start:end]
        moving = command in AUTO_INCREMENT or command in BROADCAST
        for slave in slaves:
            wkc += slave.esc.datagram(command, adp, ado, data)
            if moving:
                adp = (adp + 1) & 0xFFFF
        struct.pack_into("<H", frame, offset + 2, adp)
        WKC.pack_into(frame, end, wkc & 0xFFFF)
        offset = end + WKC.size
        if not flags & MORE:
            break
    view.release()
    frame[6] |= LOCALLY_ADMINISTERED
    return True


class StopRequest(Protocol):
    def is_set(self) -> bool: ...


class EmulatedSegment:
    """``slaves`` in a line on interface ``iface`` (a raw socket: CAP_NET_RAW);
    :meth:`serve` until a stop is requested, then :meth:`close`."""

    def __init__(self, iface: str, slaves: Sequence[EthercatDrive]) -> None:
        self.iface = iface
        self.slaves = list(slaves)
        self.frames = 0
        self.sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETHERTYPE))
        try:
            self.sock.bind((iface, ETHERTYPE))
        except OSError:
            self.sock.close()
            raise
        self.sock.settimeout(SERVICE_PERIOD_S)

    def serve(self, stop: StopRequest) -> None:
        """Answer frames, and run the drives' timers between them, until ``stop``."""
        buffer = bytearray(FRAME_MAX)
        next_service = time.monotonic()
        while not stop.is_set():
            try:
                size = self.sock.recv_into(buffer)
            except TimeoutError:
                size = 0
            if size:
                frame = buffer[:size]
                if pass_frame(self.slaves, frame):
                    self.frames += 1
                    self.sock.send(frame)
            now = time.monotonic()
            if now >= next_service:
                next_service = now + SERVICE_PERIOD_S
                for slave in self.slaves:
                    slave.service()

    def close(self) -> None:
        self.sock.close()
