"""Ways to run an emulated drive node: on a python-can bus in real time (:class:`BusRunner`,
a thread), or in lockstep on a private in-process channel (:class:`LockstepDrive`), where the
node runs whenever the master transmits and its SYNC count is the clock.

Both lockstep ways hand the nodes their frames through :func:`deliver` (the steady ones in a
:class:`~hil.emulators.drive.bank.DriveBank`'s pass): :class:`LockstepDrive`, and ``hil
emulate drive``, which wires the nodes to a
:class:`~hil.emulators.socketcand_server.SocketcandServer` (``hil.emulation.serve_drives``).
"""

from __future__ import annotations

import math
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import can

from hil.emulators.direct_bus import DirectChannel
from hil.emulators.drive.bank import DriveBank
from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.node import DriveNode, SendFn
from hil.emulators.drive.plant import AxisPlant
from hil.protocols.can_frames import Frame, frames_of
from hil.protocols.cia301 import SYNC_COB_ID


def bus_sender(bus: can.BusABC) -> SendFn:
    """A node ``send`` function writing to a python-can bus."""
    return frames_of(bus).send_frames


def deliver(nodes: Sequence[DriveNode], inboxes: Sequence[deque[Frame]], bank: DriveBank | None,
            heard_ns: int | None, *, service: bool) -> None:
    """Every frame waiting in each node's inbox (``inboxes``, node by node) handed to it: each
    steady node's cycle in ``bank``'s pass, each other node all of its own in one call in its
    turn (one with none waiting, a bus's filter having taken them away, still heard the bus
    at ``heard_ns``, the monotonic clock; None: nothing was on the bus). With ``service``,
    then the time service of each node whose last frame did not just run it (a SYNC's, on
    the master's time: time has not moved since)."""
    unserviced: list[DriveNode] = []

    def own(i: int) -> None:
        node, inbox = nodes[i], inboxes[i]
        if inbox:
            frames = list(inbox)
            inbox.clear()
            if not node.handle_frames(frames, heard_ns):
                unserviced.append(node)
            return
        if heard_ns is not None:
            node.hear(heard_ns)
        unserviced.append(node)
    if bank is None or not bank.cycle(heard_ns, own):
        for i in range(len(nodes)):
            own(i)
    if service:
        for node in unserviced:
            node.service()


class BusRunner:
    """Runs a :class:`DriveNode` on a python-can bus in a background thread (real time)."""

    def __init__(self, node: DriveNode, bus: can.BusABC, service_period_s: float = 0.001) -> None:
        self.node, self.bus = node, bus
        self._period = service_period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"drive-node-{node.node_id}",
                                        daemon=True)

    def start(self) -> BusRunner:
        self.node.boot()
        self._thread.start()
        return self

    def _run(self) -> None:
        next_service = time.monotonic()
        recv = frames_of(self.bus).recv_frame
        while not self._stop.is_set():
            try:
                frame = recv(max(0.0, next_service - time.monotonic()))
            except can.CanError:
                break  # the bus is gone
            if frame is not None:
                self.node.handle_frame(*frame)
            if time.monotonic() >= next_service:
                self.node.service()
                next_service = time.monotonic() + self._period

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)

    def __enter__(self) -> BusRunner:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()


class LockstepDrive:
    """An emulated drive on a private in-process channel (:mod:`hil.emulators.direct_bus`), run
    synchronously: every transmission on :attr:`master_bus` hands the pending frames to the
    node and runs its time service before the send returns (no threads). ``node_ids``: several
    drives on the channel instead, one axis each (``config``'s, each with its node id), all
    hearing every frame; :attr:`node` is the first.

    The node's clock is its SYNC count, so the run is deterministic and as fast as the CPU
    allows. The nodes play ``config.faults`` (``[emulator] faults``), each told to
    ``on_fault(node_id, event)`` as it starts (``event``: its ``fault``, its node time
    ``t_s``). The drive is also the master's clock in lockstep (:meth:`time_ns`,
    :meth:`sleep`):
    time passes for it when SYNCs come, so a master waiting for a state lets time pass by
    sending SYNCs.

    A steady cycle (each node's RPDO, then one SYNC, every node running CST) runs for all the
    nodes in one pass (:class:`~hil.emulators.drive.bank.DriveBank`), exactly as each node's
    own would, in less time (a lone drive's too). ``bank``: False to run every cycle through
    each node's own path.
    """

    def __init__(self, config: DriveEmulatorConfig | None = None,
                 plant: AxisPlant | None = None, *,
                 node_ids: Sequence[int] | None = None,
                 on_fault: Callable[[int, dict[str, Any]], None] | None = None,
                 bank: bool = True) -> None:
        self.channel = DirectChannel(f"hil-drive-{uuid.uuid4().hex}")
        config = config or DriveEmulatorConfig()
        if node_ids is None:
            ids = [config.node_id]
        elif plant is not None:
            raise ValueError("one plant cannot be several drives' axis")
        else:
            ids = list(node_ids)
        self._node_buses = [self.channel.attach() for _ in ids]
        self.master_bus = self.channel.attach(on_send=self.pump)
        self.nodes: list[DriveNode] = []
        try:  # a drive that cannot be (a twin's EDS that does not fit) leaves no bus open
            self.nodes = [DriveNode(replace(config, node_id=node_id), send=bus.send_frames,
                                   plant=plant, clock="sync", faults=config.faults,
                                   on_fault=self._teller(i, on_fault))
                          for i, (node_id, bus) in enumerate(
                              zip(ids, self._node_buses, strict=True))]
        except BaseException:
            self.close()
            raise
        self.node = self.nodes[0]
        if len(self.nodes) > 1:  # each node's bus takes only the frames it serves
            for node, bus in zip(self.nodes, self._node_buses, strict=True):
                bus.accept(node.hears)
                node.on_hearing_changed = self.channel.refilter
        for node in self.nodes:
            node.boot()
        self._inboxes = [bus.waiting for bus in self._node_buses]
        self._bank = DriveBank(self.nodes, self._inboxes) if bank else None

    def _teller(self, i: int, on_fault: Callable[[int, dict[str, Any]], None] | None
                ) -> Callable[[str], None] | None:
        """The ``i``-th node's fault callback: ``on_fault`` with its node id and the event."""
        if on_fault is None:
            return None

        def told(_message: str) -> None:
            node = self.nodes[i]
            on_fault(node.node_id, node.faults.events[-1])
        return told

    def attach_bus(self) -> can.BusABC:
        """One more bus on the same channel (an observer or a second master)."""
        return self.channel.attach()

    def pump(self) -> None:
        """Deliver every frame waiting for the nodes (:func:`deliver`:
        the steady ones in the bank's pass), then run the time service of each node whose
        last frame did not just run it."""
        deliver(self.nodes, self._inboxes, self._bank,
                time.monotonic_ns() if self.channel.carried_frames() else None, service=True)

    def time_ns(self) -> int:
        """The drive's time: its SYNCs so far, one communication cycle each."""
        return self.node.sync_time_ns

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` of the drive's time pass: one SYNC per communication cycle, heard
        by the drives alone (on the channel it would reach the master too, which takes a SYNC
        it did not send for another master's)."""
        period_ns = self.node.cycle_period_ns
        for _ in range(max(1, math.ceil(seconds * 1e9 / period_ns))):
            for node in self.nodes:
                node.handle_frame(SYNC_COB_ID, b"")
            self.pump()

    def close(self) -> None:
        for bus in (*self._node_buses, self.master_bus):
            bus.shutdown()
