"""The axes of a servo run, one or several: their names and nodes (``--axes x=1,y=2``, drive.toml's
``[[axis]]``, or the one axis of ``[master]``), the buses they are on with each bus's plan, the
controller they share when it is a multi-axis one, and the loop task that ticks them all
(:class:`AxesTick`): every axis' servo phases, every bus's cycle, a path's contour error
(``/path/contour``).

Each axis is one drive (its node id) with its own master, its own controller (the run's, built
once per axis with that axis' reference) and its own servo task, ticked by the one loop task of
the run (the loop's own bookkeeping, timing every phase of every task, is then paid once a tick
rather than once an axis; ``/loop/servo/timing`` times the tick of every axis, as it times the
one axis of a run that names none). The axes are on the run's bus
(``--drive`` or ``[bus]``) unless one names another (``--axes x=1,y=2@URL``,
``[[axis]] bus = URL``): every axis of a bus shares that bus's SYNC, and every bus has its cycle
and SYNC in every tick. References: ``--reference`` for every axis, or the path
``circle:radius=R,feed=F`` for two axes (a circular test, ISO 230-4: R in degrees of each axis,
F in degrees per second along the path). Parameters: ``--param KEY=V`` for every axis,
``--param NAME.KEY=V`` for axis NAME.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from can.interfaces import VALID_INTERFACES

from hil.controllers.base import UNWRAPPED, output_of, position_input_of
from hil.controllers.servo.references import contour_error
from hil.core.loop import Task
from hil.core.registry import scheme_of
from hil.core.session import Session
from hil.drivers.can_bus_time import BusPlan
from hil.drivers.canopen import parse_can_url
from hil.drivers.canopen.bus_plan import plan_axes
from hil.errors import ControllerError, UsageError
from hil.servo.config import AXIS_NAME, AxisSpec, DriveConfig, check_axes
from hil.servo.drives import RunDrives
from hil.servo.kpis import ContourKpis
from hil.servo.settings import bus_bitrate
from hil.servo.task import ServoTask

CONTOUR_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "hil.Contour",
    "description": "A path's contour error: distance of the axes' measured point (in the "
                   "path's frame: each position less its reference's offset) from the path "
                   "(> 0 outside a circle).",
    "properties": {
        "t_s": {"type": "number"},
        "x_deg": {"type": "number"},
        "y_deg": {"type": "number"},
        "contour_error_deg": {"type": "number", "x-cdr": "float32"},
    },
}


def parse_axes(text: str) -> tuple[AxisSpec, ...]:
    """``x=1,y=2@URL`` -> the axes, in order (an axis without ``@URL`` on the run's bus); a
    clear error for anything else."""
    axes = []
    for item in filter(None, (part.strip() for part in text.split(","))):
        axis, at, bus = item.partition("@")
        name, eq, node = axis.partition("=")
        if not eq or not AXIS_NAME.fullmatch(name) or not node.isdigit() or \
                not 1 <= int(node) <= 127 or (at and not bus.strip()):
            raise UsageError(f"--axes {text!r}: {item!r} is not NAME=NODE[@URL] (a lower-case "
                             "name, a CANopen node id 1..127, the URL of its bus when it is "
                             "not the run's), e.g. --axes x=1,y=2 or --axes "
                             "x=1,y=1@socketcand://127.0.0.1:29536")
        axes.append(AxisSpec(name, int(node), bus=bus.strip()))
    return check_axes(tuple(axes), f"--axes {text!r}")


def bus_key(url: str, channel: str) -> str:
    """One bus, one name: a python-can or socketcand URL as its parts say it (so two spellings
    of one bus are one bus); another scheme's URL as it is."""
    if scheme_of(url) not in VALID_INTERFACES:
        return url
    return parse_can_url(url, channel).url


@dataclass(frozen=True)
class BusAxes:
    """The axes on one bus, in the run's order, and the plan of that bus."""

    url: str
    axes: tuple[AxisSpec, ...]
    plan: BusPlan


def carries_can(url: str) -> bool:
    """Whether the bus at ``url`` is CAN (its time budget planned), not an EtherCAT segment
    (one frame of microseconds a cycle, whatever the axes)."""
    return scheme_of(url) != "ethercat"


def bus_lock_key(url: str) -> str:
    """What a run locks of the bus at ``url``: the bus; of an EtherCAT segment the segment,
    whichever slave the URL names (one master a segment)."""
    return url.partition("?")[0] if scheme_of(url) == "ethercat" else url


def plan_buses(axes: tuple[AxisSpec, ...], run_url: str, drive: DriveConfig
               ) -> list[BusAxes]:
    """The buses of ``axes`` (an axis without a bus of its own on ``run_url``), in the order
    they first appear, each planned at its bit rate (:func:`plan_axes`). Several axes name
    each bus as its parts say it (two spellings of one bus are one bus); a lone axis keeps
    ``run_url`` as given."""
    master = drive.master
    if len(axes) == 1:
        placed: tuple[AxisSpec, ...] = (replace(axes[0], bus=axes[0].bus or run_url),)
    else:
        placed = check_axes(tuple(replace(axis, bus=bus_key(axis.bus or run_url,
                                                             master.channel))
                                  for axis in axes), "the axes")
    buses = []
    for url in dict.fromkeys(axis.bus for axis in placed):
        on_bus = tuple(axis for axis in placed if axis.bus == url)
        plan = plan_axes(master, [axis.name for axis in on_bus], bus_bitrate(url, drive))
        buses.append(BusAxes(url, on_bus, plan))
    return buses


class SharedStep:
    """A multi-axis controller (``multi_axis = True``, built as ``Class(references,
    params)``, ``step(positions_deg: np.ndarray, t_s) -> currents_mA``) stepped once a tick
    with every axis' position (all read by then; ``position % 360``, or multi-turn as its
    ``position_input`` says), its currents kept for the axes' tasks."""

    def __init__(self, whole: Any, tasks: list[ServoTask], label: str) -> None:
        self.whole, self.tasks, self.label = whole, tasks, label
        self.unwrapped = position_input_of(whole, label) == UNWRAPPED
        self._t_s: float | None = None
        self._currents = np.zeros(0)

    def currents(self, t_s: float) -> np.ndarray:
        if self._t_s != t_s:  # the first axis of this tick steps the controller
            positions = np.array([task.feedback.position_deg for task in self.tasks])
            if not self.unwrapped:
                positions %= 360.0
            currents = np.asarray(self.whole.step(positions, t_s), dtype=float)
            if currents.shape != positions.shape:
                raise ControllerError(
                    f"controller {self.label!r}: a multi-axis step() must return one current "
                    f"per axis ({positions.size}), got shape {currents.shape}")
            self._t_s, self._currents = t_s, currents
        return self._currents


class AxisShare:
    """One axis' view of a :class:`SharedStep`: the servo contract for its task (what it
    returns, the whole controller's ``output``)."""

    def __init__(self, shared: SharedStep, index: int) -> None:
        self.shared, self.index = shared, index
        self.output = output_of(shared.whole, shared.label)

    def step(self, position_deg: float, t_s: float) -> float:
        return float(self.shared.currents(t_s)[self.index])


class AxesTick(Task):
    """The loop's one task for named axes: each phase of every axis' :class:`ServoTask` in the
    run's order (every feedback read before any controller steps), then the cycle on every bus
    (each axis' RPDO, one SYNC a bus) and the path's contour error."""

    def __init__(self, session: Session, buses: RunDrives, tasks: list[ServoTask],
                 radius: float | None, settle_s: float) -> None:
        super().__init__("servo")
        self.buses, self.tasks, self.radius = buses, tasks, radius
        self.loop = session.loop
        self.dt = tasks[0].dt  # every axis' task ticks on the loop's base period
        self.settle_s = settle_s
        self.topic = session.topic("/path/contour", CONTOUR_SCHEMA, high_rate=True) \
            if radius is not None else None
        # every axis' feedback and command of a tick, handed to the writer in one record
        self.rows = session.recorder.rows(tuple(
            topic for task in tasks for topic in (task.feedbacks, task.commands)))
        self.max_error = 0.0
        self.sum_squares = 0.0
        self.counted = 0
        self.cycles = 0  # cycles put on the bus while ticking

    def read(self, t_ns: int) -> None:
        for task in self.tasks:
            task.read(t_ns)

    def compute(self, t_ns: int) -> None:
        """Every axis' step, at the tick's number and time worked out once."""
        n = self.loop.tick_number
        t_s = n * self.dt
        for task in self.tasks:
            task.compute_at(n, t_s)

    def write(self, t_ns: int) -> None:
        for task in self.tasks:
            task.write(t_ns)
        self.buses.end_cycle()
        self.cycles += 1

    def record(self, t_ns: int) -> None:
        """Every axis' rows in one hand-over, then every axis' checks, then the contour."""
        tasks = self.tasks
        rows: list[tuple[object, ...]] = []
        for task in tasks:
            rows += task.rows()
        self.rows.log(t_ns, tuple(rows))
        late_us = tasks[0].late_us(t_ns)  # the tick's, every axis'
        for task in tasks:
            task.check(t_ns, late_us)
        if self.topic is None or self.radius is None:
            return
        x_task, y_task = self.tasks[0], self.tasks[1]
        x = x_task.feedback.position_deg - x_task.reference_offset_deg
        y = y_task.feedback.position_deg - y_task.reference_offset_deg
        error = float(contour_error(x, y, self.radius))
        t_s = x_task.t_s
        self.topic.log(t_ns, (t_s, x, y, error))
        if t_s >= self.settle_s - 1e-12:
            self.counted += 1
            self.sum_squares += error * error
            self.max_error = max(self.max_error, abs(error))

    def kpis(self) -> ContourKpis:
        return ContourKpis(self.radius, self.max_error if self.counted else None,
                           math.sqrt(self.sum_squares / self.counted) if self.counted else None)


