"""Several drives on one bus, cycled together: one SYNC per cycle, every RPDO of the cycle on
the bus before it, each drive's TPDOs handed to its own master.

:class:`AxisBus` sits between one :class:`~hil.drivers.canopen.link.CanLink` and one
:class:`~hil.drivers.canopen.master.CanDriveMaster` per drive: each master talks to a
:class:`NodeLink` (the ``CanLink`` interface) and stays what it is for one drive. The bus

* routes every received frame to the master of the node its COB-ID names (EMCY, TPDOs, SDO
  answers, heartbeats carry the node id in their low 7 bits); NMT, SYNC, the master's own
  heartbeat id and frames of nodes it does not drive go to every master (each ignores what is
  not its own, and each watches for another master on the bus);
* passes every transmission through while the drives are set up (NMT, SDO), and once
  :meth:`AxisBus.cycle_together` is on, holds each master's cycle (a queued SDO download, the
  RPDO) until :meth:`AxisBus.end_cycle`, which puts them all on the bus in one transmission,
  axis by axis, followed by one SYNC and one heartbeat of the master (every master's are the
  same frames: the first one's is sent, so a SYNC counter is the first master's).

:class:`AxisGroup` drives the group: start every axis, then the cyclic exchange, and stop them
together - quick stop on every axis in the same cycles until all stand, then disable voltage,
in one cycle too.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Protocol

from hil.drivers.canopen.cyclic import Feedback
from hil.drivers.canopen.errors import DriveError
from hil.drivers.canopen.link import CanLink
from hil.drivers.canopen.master import CanDriveMaster
from hil.drivers.canopen.stopping import stop_together
from hil.protocols.can_frames import Frame
from hil.protocols.cia301 import HEARTBEAT_BASE, NMT_COB_ID, SYNC_COB_ID

NODE_ID_BITS = 0x7F
TPDO_IDS_FIRST, TPDO_IDS_LAST = 0x181, 0x4FF  # TPDO1-4 of nodes 1-127, default COB-IDs


class NodeLink:
    """One master's view of an :class:`AxisBus`: the :class:`CanLink` interface."""

    def __init__(self, bus: AxisBus, node_id: int) -> None:
        self._bus = bus
        self.node_id = node_id
        self._watched: frozenset[int] = frozenset()
        self.inbox: deque[Frame] = deque()
        self.send: Callable[[list[Frame]], None] = bus.send  # held until the cycle ends

    @property
    def watched_ids(self) -> frozenset[int]:
        return self._watched

    @watched_ids.setter
    def watched_ids(self, ids: frozenset[int]) -> None:
        """The master's own ids (set once, when it is built): the bus watches them all."""
        self._watched = ids
        self._bus.link.watched_ids = frozenset().union(*(n.watched_ids for n in
                                                         self._bus.nodes if n is not self),
                                                       ids)

    @property
    def name(self) -> str:
        return self._bus.link.name

    @property
    def syncs_sent(self) -> int:
        """The SYNCs of the bus: one a cycle for every axis."""
        return self._bus.link.syncs_sent

    def recv(self, timeout: float | None) -> Frame | None:
        inbox = self.inbox
        if inbox:  # routed here already
            return inbox.popleft()
        if timeout is not None and timeout <= 0:
            waiting = self._bus.link.waiting
            if waiting is not None and not waiting:
                return None  # nor is anything on the bus: each master looks twice a cycle
        return self._bus.recv(self, timeout)

    def own_echo(self, frame: Frame) -> bool:
        """Echoes of the group's own frames never reach a master (the bus drops them)."""
        return False

    def reconnect(self) -> None:
        self._bus.link.reconnect()

    def shutdown(self) -> None:
        self._bus.release(self)


class AxisBus:
    """Several masters on one :class:`CanLink`: frames routed by node, cycles sent together."""

    def __init__(self, link: CanLink, node_ids: Sequence[int], *,
                 master_heartbeat_id: int = 127) -> None:
        if len(set(node_ids)) != len(node_ids) or not node_ids:
            raise DriveError(f"an axis bus needs distinct node ids, got {list(node_ids)}")
        self.link = link
        self.nodes = [NodeLink(self, node_id) for node_id in node_ids]
        self._by_id = {node.node_id: node for node in self.nodes}
        self._broadcast = {NMT_COB_ID, SYNC_COB_ID, HEARTBEAT_BASE + master_heartbeat_id}
        # the SYNC and the master's heartbeat: one of each a cycle (the first master's)
        self._once = frozenset((SYNC_COB_ID, HEARTBEAT_BASE + master_heartbeat_id))
        self.together = False
        self._held: list[Frame] = []
        self._sync: dict[int, Frame] = {}  # this cycle's SYNC and master heartbeat (the first)
        self._open = len(self.nodes)
        self.cycles = 0  # cycles put on the bus together (one SYNC each)
        # the inbox of each COB-ID seen that goes to one master alone without an echo check
        # (a drive's TPDOs...), for the link's watched ids it was worked out with
        self._routes: dict[int, deque[Frame]] = {}
        self._routes_for = link.watched_ids

    def node_link(self, node_id: int) -> NodeLink:
        return self._by_id[node_id]

    def cycle_together(self, on: bool = True) -> None:
        """From now on (``on``) hold the masters' cycles until :meth:`end_cycle`. The TPDOs
        still waiting then answer the set-up's SYNCs (a drive enabled while the next one was
        set up), no cycle's: they are dropped."""
        self.together = on
        self._held, self._sync = [], {}
        if on:
            self._route_waiting()
            for node in self.nodes:
                kept = [frame for frame in node.inbox
                        if not TPDO_IDS_FIRST <= frame[0] <= TPDO_IDS_LAST]
                node.inbox.clear()
                node.inbox.extend(kept)

    # -- sending ------------------------------------------------------------------------------
    def send(self, frames: list[Frame]) -> None:
        """A master's frames: on the bus at once while setting up, else held for
        :meth:`end_cycle`."""
        if not self.together:
            self.link.send(frames)
            return
        held, shared, once = self._held, self._sync, self._once
        for frame in frames:
            if frame[0] in once:
                shared.setdefault(frame[0], frame)
            else:
                held.append(frame)

    def end_cycle(self) -> None:
        """Every frame the masters sent for this cycle, in their order, then one SYNC (and
        one heartbeat of the master, when one was due), in one transmission."""
        out, shared = self._held, self._sync
        if shared:
            sync = shared.pop(SYNC_COB_ID, None)
            if sync is not None:
                out.append(sync)
            out.extend(shared.values())  # the master's heartbeat
        self._held, self._sync = [], {}
        if out:
            self.link.send(out)
            self.cycles += 1

    # -- receiving ----------------------------------------------------------------------------
    def recv(self, node: NodeLink, timeout: float | None) -> Frame | None:
        """``node``'s next frame, reading the bus (and routing what is for others) for at most
        ``timeout`` seconds (0: only what is already here). Frames already received are all
        routed before the time-out counts: another drive's frame ahead of this one's never
        makes this one late."""
        inbox, link, route = node.inbox, self.link, self._route
        self._route_waiting()  # all already here, routed, before a wait
        if inbox:
            return inbox.popleft()
        if timeout is not None and timeout <= 0:
            return None
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                return None
            frame = link.recv(remaining)
            if frame is None:
                return None
            route(frame)
            while not inbox and (frame := link.recv(0)) is not None:
                route(frame)
            if inbox:
                return inbox.popleft()

    def _route_waiting(self) -> None:
        """Every frame already here, to its master's inbox: taken in one call where the link
        can (then each COB-ID routed before goes by :attr:`_routes`), else frame by frame."""
        link, route = self.link, self._route
        if not link.takes_frames:
            while (frame := link.recv(0)) is not None:
                route(frame)
            return
        frames = link.take_frames()
        if not frames:
            return
        if link.watched_ids is not self._routes_for:
            self._routes, self._routes_for = {}, link.watched_ids
        routes = self._routes
        for frame in frames:
            inbox = routes.get(frame[0])
            if inbox is None:
                route(frame)
            else:
                inbox.append(frame)

    def _route(self, frame: Frame) -> None:
        can_id = frame[0]
        link = self.link
        watched = can_id in link.watched_ids
        if watched and link.own_echo(frame):
            return  # the group's own SYNC / NMT / heartbeat, handed back by an echoing bus
        owner = self._by_id.get(can_id & NODE_ID_BITS)
        if owner is not None and can_id not in self._broadcast:
            owner.inbox.append(frame)
            if not watched and link.watched_ids is self._routes_for:
                self._routes[can_id] = owner.inbox
        else:
            for node in self.nodes:
                node.inbox.append(frame)

    def release(self, node: NodeLink) -> None:
        """A master is done with its link; the bus closes with the last one."""
        self._open -= 1
        if self._open == 0:
            self.link.shutdown()


class CycledDrives(Protocol):
    """Drives cycled together (an :class:`AxisGroup`, or a master alone on its bus with a
    cycle that needs no ending): what :meth:`AxisGroup.stop_together` stops."""

    @property
    def masters(self) -> Sequence[CanDriveMaster]: ...

    def end_cycle(self) -> None: ...


class AxisGroup:
    """The masters of several drives on one :class:`AxisBus` (each
    :class:`CanDriveMaster` built on its node's :class:`NodeLink`), started, cycled and
    stopped together."""

    def __init__(self, bus: AxisBus, masters: Sequence[CanDriveMaster]) -> None:
        self.bus = bus
        self.masters = list(masters)

    def start(self) -> list[Feedback]:
        """Every drive set up, then every drive enabled, then the cycles sent together."""
        self.bus.cycle_together(False)
        for master in self.masters:
            master.open()
            master.configure()
        for master in self.masters:
            master.enable()
        self.bus.cycle_together(True)
        return [master.receive_feedback() for master in self.masters]

    def send_currents(self, currents_ma: Sequence[float]) -> None:
        """One cycle: each axis' current (CST), then the one SYNC."""
        for master, current in zip(self.masters, currents_ma, strict=True):
            master.send_command(current)
        self.bus.end_cycle()

    def end_cycle(self) -> None:
        """The cycle the masters sent, on the bus behind one SYNC (:meth:`AxisBus.end_cycle`)."""
        self.bus.end_cycle()

    def receive(self) -> list[Feedback]:
        """Each axis' TPDOs of the last SYNC."""
        return [master.receive_feedback() for master in self.masters]

    def safe_state(self) -> None:
        """Quick stop on every axis in the same cycles until all stand, then disable voltage
        in one cycle (:meth:`stop_together`); silent."""
        if self.bus.together:
            self.stop_together([self])
        else:  # still setting up: one drive after the other
            for master in self.masters:
                master.safe_state()

    @staticmethod
    def stop_together(groups: Sequence[CycledDrives]) -> None:
        """Every enabled axis of ``groups`` (one bus each, cycling together) stopped in the same
        cycles (:func:`~hil.drivers.canopen.stopping.stop_together`): each cycle every axis'
        frames, then every bus's :meth:`~AxisBus.end_cycle`. Silent."""
        def end_cycles() -> None:
            for group in groups:
                group.end_cycle()

        stop_together([master for group in groups for master in group.masters], end_cycles)

    def close(self) -> None:
        """Stop together, then release every master (and the bus with the last); their
        frames go straight to the bus again first (a master puts its drive's settings back
        by SDO on its way out)."""
        try:
            self.safe_state()
        finally:
            self.bus.cycle_together(False)
            for master in self.masters:
                master.disconnect()
