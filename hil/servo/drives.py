"""The drives of a servo run, bus by bus: one master per axis, cycled and stopped together.

A bus with one axis gives its master the bus to itself: the master sends its own cycle (its
RPDO, then the SYNC). A bus with several holds every master's cycle in an
:class:`~hil.drivers.canopen.axes.AxisGroup` until :meth:`RunDrives.end_cycle` puts them all out
behind one SYNC. A stop of any kind stops every axis of every bus in the same cycles
(:meth:`~hil.drivers.canopen.axes.AxisGroup.stop_together`); for one axis that is its master's
own safe stop.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from hil.drivers.canopen.axes import AxisGroup
from hil.drivers.canopen.master import CanDriveMaster


class CycledBus(Protocol):
    """A bus several masters cycle together: a CAN
    :class:`~hil.drivers.canopen.axes.AxisBus`, an EtherCAT segment."""

    together: bool

    def cycle_together(self, on: bool = True) -> None: ...

    def end_cycle(self) -> None: ...


class AxesOnABus(Protocol):
    """The group of a bus with several axes (:class:`AxisGroup`, or EtherCAT's)."""

    @property
    def bus(self) -> CycledBus: ...


@dataclass
class BusDrives:
    """The masters of one bus, in the axes' order; ``group``: their
    :class:`~hil.drivers.canopen.axes.AxisGroup` when they are several (None: one master,
    alone on its bus); ``closers``: what else the bus was opened with (an emulator, a
    ``--can-log`` file), closed after the masters."""

    url: str
    masters: list[CanDriveMaster]
    group: AxesOnABus | None = None
    closers: tuple[Callable[[], None], ...] = ()

    @property
    def together(self) -> bool:
        """Whether the bus's cycles are held for :meth:`end_cycle` (a lone master's always
        are: it sends its own)."""
        return self.group is None or self.group.bus.together

    def cycle_together(self, on: bool) -> None:
        if self.group is not None:
            self.group.bus.cycle_together(on)

    def end_cycle(self) -> None:
        if self.group is not None:
            self.group.bus.end_cycle()

    def disconnect(self) -> None:
        """Every master released (the bus with its last), then the closers."""
        try:
            for master in self.masters:
                master.disconnect()
        finally:
            for close in self.closers:
                close()


class RunDrives:
    """Every bus of a run: started bus by bus, cycled in every tick, stopped together (quick
    stop on every axis in the same cycles until all stand, then disable voltage in one cycle
    too)."""

    def __init__(self, buses: Sequence[BusDrives] = ()) -> None:
        self.buses = list(buses)

    @property
    def masters(self) -> list[CanDriveMaster]:
        return [master for bus in self.buses for master in bus.masters]

    def add(self, bus: BusDrives) -> None:
        self.buses.append(bus)

    def cycle_together(self) -> None:
        for bus in self.buses:
            bus.cycle_together(True)

    def end_cycle(self) -> None:
        """Every bus's cycle: its axes' RPDOs, then its SYNC."""
        for bus in self.buses:
            bus.end_cycle()

    def safe_state(self) -> None:
        """Every axis stopped in the same cycles; silent."""
        if all(bus.together for bus in self.buses):
            AxisGroup.stop_together(self.buses)
        else:  # still setting up: one drive after the other
            for master in self.masters:
                master.safe_state()

    def close(self) -> None:
        """Stop together, then release every bus, each passing frames through again first: a
        master's last SDO writes (its drive's own limits back) are no cycle's."""
        try:
            self.safe_state()
        finally:
            for bus in self.buses:
                bus.cycle_together(False)
            for bus in self.buses:
                bus.disconnect()
