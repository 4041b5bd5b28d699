"""Bus time of the cyclic CANopen traffic on classic CAN, and whether a cycle period fits.

Bits of one classic CAN data frame with ``n`` data bytes, standard 11-bit identifier:
SOF 1 + identifier 11 + RTR 1 + IDE 1 + r0 1 + DLC 4 + data 8n + CRC 15 + CRC delimiter 1 +
ACK 2 + EOF 7 + intermission 3 = 47 + 8n bits (extended 29-bit identifier: 67 + 8n).
Bit stuffing adds one bit after five equal bits in SOF..CRC (34 + 8n bits standard, 54 + 8n
extended): none in the best case, at most floor((34 + 8n - 1) / 4) in the worst case.
So at 1 Mbit/s an 8-byte frame takes 111 us without stuffing and up to 135 us with it.

**One figure, the worst case.** A cycle is judged and reported by its *worst-case bus time*:
every frame of the cycle with all the stuff bits it can take (heartbeats at their average
share per cycle). The rule: the worst-case bus time must not exceed the cycle period, with no
margin on top. Why this figure: it is the bound the wire cannot exceed whatever the data, so a
cycle within it is always on the bus before the next SYNC is due (a cycle that spills over
delays that SYNC, and with it every drive's sampling instant). Why no more margin: real data
stuffs only a few bits per frame (one CST axis at 1 Mbit/s: 317 us without any stuffing against
the 381 us of the worst case), and that difference is the room left for what the plan does not
count (an SDO download, an EMCY). The figure without stuffing is a best case no cycle is sure
of; it is not reported.

Classic CAN's bit rate is at most 1 Mbit/s (:data:`CLASSIC_CAN_MAX_BITRATE`); a CAN FD bus
takes more (hil's frames on it are still classic ones, counted here at the bus's bit rate).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

#: the highest bit rate of classic CAN (ISO 11898-1), bit/s
CLASSIC_CAN_MAX_BITRATE = 1_000_000
#: the highest bit rate hil takes for a CAN FD bus (its data phase; transceivers stop at
#: 8 Mbit/s), bit/s
CAN_FD_MAX_BITRATE = 8_000_000
#: how the one figure is worked out, as outputs say it
WORST_CASE = "worst case: every frame with all the stuff bits it can take"


@dataclass(frozen=True)
class FrameLoad:
    """One kind of frame on the bus: ``per_cycle`` frames of ``data_bytes`` each per cycle
    (fractional for slower traffic such as heartbeats: period / heartbeat period)."""

    name: str
    data_bytes: int
    per_cycle: float = 1.0
    extended: bool = False

    def __post_init__(self) -> None:
        if not 0 <= self.data_bytes <= 8:
            raise ValueError(f"{self.name}: classic CAN carries 0..8 data bytes, "
                             f"got {self.data_bytes}")
        if self.per_cycle < 0:
            raise ValueError(f"{self.name}: frames per cycle must be >= 0")


def frame_bits(data_bytes: int, *, extended: bool = False, worst_case: bool = False) -> int:
    """Bits on the wire for one data frame, intermission included."""
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"classic CAN carries 0..8 data bytes, got {data_bytes}")
    fixed, stuffable = (67, 54) if extended else (47, 34)
    bits = fixed + 8 * data_bytes
    if worst_case:
        bits += (stuffable + 8 * data_bytes - 1) // 4
    return bits


def max_bitrate(fd: bool) -> int:
    """The highest bit rate of a bus, bit/s: classic CAN's, or CAN FD's (``fd``)."""
    return CAN_FD_MAX_BITRATE if fd else CLASSIC_CAN_MAX_BITRATE


@dataclass(frozen=True)
class BusBudget:
    """Bus time per cycle against the cycle period (times in microseconds): ``worst_us`` is
    the figure a cycle is judged by (see the module), ``nominal_us`` the same frames without
    any stuff bit (kept in the drive's record, never judged by)."""

    bitrate: int
    period_us: float
    nominal_us: float
    worst_us: float
    frames: tuple[FrameLoad, ...]
    warnings: tuple[str, ...] = field(default=())

    @property
    def fits(self) -> bool:
        """True when the worst-case bus time is within the period."""
        return self.worst_us <= self.period_us

    @property
    def load_nominal(self) -> float:
        return self.nominal_us / self.period_us

    @property
    def load_worst(self) -> float:
        return self.worst_us / self.period_us

    def summary(self) -> dict[str, float | int | bool | list[str]]:
        """The record of ``drive.configured``: both bounds, ``fits`` judged by the worst."""
        return {
            "bitrate": self.bitrate, "period_us": self.period_us,
            "nominal_us": round(self.nominal_us, 1), "worst_us": round(self.worst_us, 1),
            "load_nominal": round(self.load_nominal, 3), "load_worst": round(self.load_worst, 3),
            "fits": self.fits, "warnings": list(self.warnings),
        }


def cycle_budget(bitrate: int, period_s: float, frames: Iterable[FrameLoad]) -> BusBudget:
    """Bus time of ``frames`` per cycle at ``bitrate`` against ``period_s``, with a warning
    when the worst case does not fit."""
    if bitrate <= 0:
        raise ValueError(f"bitrate must be > 0 bit/s, got {bitrate}")
    if not period_s > 0:
        raise ValueError(f"cycle period must be > 0 s, got {period_s}")
    frames = tuple(frames)
    us_per_bit = 1e6 / bitrate
    nominal = sum(f.per_cycle * frame_bits(f.data_bytes, extended=f.extended) for f in frames)
    worst = sum(f.per_cycle * frame_bits(f.data_bytes, extended=f.extended, worst_case=True)
                for f in frames)
    nominal_us, worst_us, period_us = nominal * us_per_bit, worst * us_per_bit, period_s * 1e6
    warnings = []
    if worst_us > period_us:
        warnings.append(
            f"the cyclic CAN traffic needs {worst_us:.0f} us per cycle at {bitrate} bit/s "
            f"({WORST_CASE}): more than the {period_us:.0f} us period")
    return BusBudget(bitrate, period_us, nominal_us, worst_us, frames, tuple(warnings))


@dataclass(frozen=True)
class AxisTraffic:
    """One axis' share of a bus cycle: its RPDO, its TPDOs and its heartbeat (0: none)."""

    name: str
    rpdo_bytes: int = 4
    tpdo_bytes: tuple[int, ...] = (6, 6)
    heartbeat_period_s: float = 0.1

    def frames(self, period_s: float) -> list[FrameLoad]:
        frames = [FrameLoad(f"{self.name} RPDO1", self.rpdo_bytes)]
        frames += [FrameLoad(f"{self.name} TPDO{i}", n)
                   for i, n in enumerate(self.tpdo_bytes, start=1)]
        if self.heartbeat_period_s > 0:
            frames.append(FrameLoad(f"{self.name} heartbeat", 1,
                                    per_cycle=period_s / self.heartbeat_period_s))
        return frames


@dataclass(frozen=True)
class BusPlan:
    """Several axes on one bus, one SYNC per cycle: the budget, and where the limits are
    (by the worst-case bus time): ``max_axes`` axes like the first fit this period, these
    axes fit periods from ``min_period_us`` on, and ``lean_us``, their bus time with fewer
    mapped objects (``lean_how`` says how; None: nothing left to drop)."""

    budget: BusBudget
    axes: tuple[AxisTraffic, ...]
    max_axes: int
    min_period_us: float
    lean_us: float | None = None
    lean_how: str = ""

    @property
    def fits(self) -> bool:
        return self.budget.fits

    @property
    def bus_time_us(self) -> float:
        """The one figure: the worst-case bus time of a cycle."""
        return self.budget.worst_us

    def problem(self, period_note: str = "") -> str | None:
        """Why the plan does not fit, with the figure and every way out, each as the setting
        that takes it (None: it fits); ``period_note``: said of the longer cycle (which of
        them the controller runs at)."""
        if self.fits:
            return None
        b, n = self.budget, len(self.axes)
        ways = [f"a longer cycle: master.cycle_period_us >= {math.ceil(self.min_period_us)} "
                f"({1e6 / self.min_period_us:.0f} Hz or slower{period_note})"]
        if self.max_axes >= 1:
            buses = -(-n // self.max_axes)
            fit = "fits" if self.max_axes == 1 else "fit"
            ways.append(f"{buses} buses, {_axes(self.max_axes)} per bus ({fit} this period: "
                        "--axes x=1,y=2@URL or [[axis]] bus = URL)")
        else:
            ways.append("another bus does not help: one axis alone does not fit this period")
        if self.lean_us is not None:
            enough = "fits" if self.lean_us <= b.period_us else "not enough alone"
            ways.append(f"fewer mapped objects: {self.lean_how}: {self.lean_us:.0f} us, "
                        f"{enough}")
        return (f"{_axes(n)} need{'s' if n == 1 else ''} {b.worst_us:.0f} us of bus time per "
                f"cycle at {b.bitrate} bit/s ({WORST_CASE}): more than the "
                f"{b.period_us:.0f} us period; ways out: {'; '.join(ways)}")

    def summary(self) -> dict[str, float | int | bool | str | None]:
        """The plan as ``hil drive plan --json`` prints it and a run records it (``bus_plan``):
        the one figure, ``bus_time_us``, and how it is worked out, ``bus_time``."""
        b = self.budget
        return {"bitrate": b.bitrate, "period_us": b.period_us,
                "bus_time_us": round(b.worst_us, 1), "bus_time": WORST_CASE,
                "load": round(b.load_worst, 3), "fits": self.fits, "axes": len(self.axes),
                "max_axes": self.max_axes, "min_period_us": round(self.min_period_us, 1),
                "lean_us": None if self.lean_us is None else round(self.lean_us, 1),
                "problem": self.problem()}


def _axes(n: int) -> str:
    return "1 axis" if n == 1 else f"{n} axes"


def bus_frames(period_s: float, axes: Iterable[AxisTraffic],
               master_heartbeat_s: float = 0.0) -> list[FrameLoad]:
    """One cycle of a bus: one SYNC, then every axis' frames, then the master's heartbeat."""
    frames = [FrameLoad("SYNC", 0)]
    for axis in axes:
        frames += axis.frames(period_s)
    if master_heartbeat_s > 0:
        frames.append(FrameLoad("master heartbeat", 1, per_cycle=period_s / master_heartbeat_s))
    return frames


def plan_bus(bitrate: int, period_s: float, axes: Iterable[AxisTraffic],
             master_heartbeat_s: float = 0.0, lean: Iterable[AxisTraffic] = (),
             lean_how: str = "") -> BusPlan:
    """The plan of ``axes`` sharing one bus at ``bitrate``, cycled every ``period_s``;
    ``lean``: the same axes with fewer mapped objects (``lean_how``: the setting that maps
    them so), for the ways out."""
    axes = tuple(axes)
    if not axes:
        raise ValueError("a bus plan needs at least one axis")
    budget = cycle_budget(bitrate, period_s, bus_frames(period_s, axes, master_heartbeat_s))
    us_per_bit = 1e6 / bitrate

    def worst_us(frames: list[FrameLoad]) -> float:
        return us_per_bit * sum(f.per_cycle * frame_bits(f.data_bytes, worst_case=True)
                                for f in frames)

    # heartbeats take a share per cycle proportional to the period: worst(T) = fixed + r T
    fixed = worst_us([f for f in bus_frames(period_s, axes, master_heartbeat_s)
                      if "heartbeat" not in f.name])
    rate = (worst_us(bus_frames(period_s, axes, master_heartbeat_s)) - fixed) / (period_s * 1e6)
    min_period_us = fixed / (1.0 - rate) if rate < 1.0 else float("inf")
    shared = worst_us(bus_frames(period_s, [], master_heartbeat_s))
    per_axis = worst_us(axes[0].frames(period_s))
    max_axes = max(0, int((budget.period_us - shared) // per_axis))
    lean = tuple(lean)
    lean_us = worst_us(bus_frames(period_s, lean, master_heartbeat_s)) if lean else None
    return BusPlan(budget, axes, max_axes, min_period_us, lean_us, lean_how)
