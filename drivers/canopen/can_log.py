"""Every CAN frame of a link written to a file python-can's tools read (``--can-log``):
``.blf`` (Vector), ``.asc``, ``.trc`` (PEAK), ``.log`` (candump), ``.csv`` - whatever
``can.Logger`` picks by the file's suffix. Frames are stamped with the wall clock when the
master sends or receives them and written by a thread of their own, so the cyclic exchange
only appends to a queue."""

from __future__ import annotations

import queue
import threading
import time

import can

from hil.drivers.canopen.errors import DriveError
from hil.drivers.errors import DriverSetupError
from hil.protocols.can_frames import Frame

SUFFIXES = (".blf", ".asc", ".trc", ".log", ".csv")


class CanLog:
    """A :class:`~hil.drivers.canopen.link.FrameTrace` writing to ``path`` (its suffix chooses the
    format); :meth:`close` writes what is queued and finishes the file."""

    def __init__(self, path: str, channel: str = "can0") -> None:
        if not path.lower().endswith(SUFFIXES):
            raise DriverSetupError(f"--can-log {path}: the file's suffix names its format, one of "
                              f"{', '.join(SUFFIXES)}")
        try:
            self._writer = can.Logger(path)
        except (OSError, ValueError) as exc:
            raise DriverSetupError(f"--can-log {path}: cannot write it: {exc}") from None
        self.path, self.channel = path, channel
        self.frames = 0
        self._queue: queue.SimpleQueue[tuple[float, Frame, bool] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._write, name="can-log", daemon=True)
        self._thread.start()

    def sent(self, frames: list[Frame]) -> None:
        now = time.time()
        for frame in frames:
            self._queue.put((now, frame, False))

    def received(self, frame: Frame) -> None:
        self._queue.put((time.time(), frame, True))

    def _write(self) -> None:
        while (item := self._queue.get()) is not None:
            stamp, (can_id, data), rx = item
            self._writer.on_message_received(can.Message(
                timestamp=stamp, arbitration_id=can_id, data=data, is_extended_id=False,
                is_rx=rx, channel=self.channel))
            self.frames += 1

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=10)
        try:
            self._writer.stop()
        except OSError as exc:
            raise DriveError(f"--can-log {self.path}: {exc}") from None
