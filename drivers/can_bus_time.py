"""Bus time of the cyclic CANopen traffic on classic CAN, and whether a cycle period fits.

Bits of one classic CAN data frame with ``n`` data bytes, standard 11-bit identifier:
SOF 1 + identifier 11 + RTR 1 + IDE 1 + r0 1 + DLC 4 + data 8n + CRC 15 + CRC delimiter 1 +
ACK 2 + EOF 7 + intermission 3 = 47 + 8n bits (extended 29-bit identifier: 67 + 8n).
Bit stuffing adds one bit after five equal bits in SOF..CRC (34 + 8n bits standard, 54 + 8n
extended): none in the best case, at most floor((34 + 8n - 1) / 4) in the worst case.

So at 1 Mbit/s an 8-byte frame takes 111 us without stuffing (DESIGN.md's "about 111 us" is this
nominal figure, intermission included) and up to 135 us with worst-case stuffing. Typical data
stuffs a few bits; both bounds are reported and a period is judged against both:

* nominal time > period: the cycle cannot fit at all;
* worst-case time > period: it fits only if the data happens to stuff little.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field


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


@dataclass(frozen=True)
class BusBudget:
    """Bus time per cycle against the cycle period (times in microseconds)."""

    bitrate: int
    period_us: float
    nominal_us: float
    worst_us: float
    frames: tuple[FrameLoad, ...]
    warnings: tuple[str, ...] = field(default=())

    @property
    def fits(self) -> bool:
        """True when even worst-case bit stuffing leaves the cycle within the period."""
        return self.worst_us <= self.period_us

    @property
    def load_nominal(self) -> float:
        return self.nominal_us / self.period_us

    @property
    def load_worst(self) -> float:
        return self.worst_us / self.period_us

    def summary(self) -> dict[str, float | int | bool | list[str]]:
        return {
            "bitrate": self.bitrate, "period_us": self.period_us,
            "nominal_us": round(self.nominal_us, 1), "worst_us": round(self.worst_us, 1),
            "load_nominal": round(self.load_nominal, 3), "load_worst": round(self.load_worst, 3),
            "fits": self.fits, "warnings": list(self.warnings),
        }


def cycle_budget(bitrate: int, period_s: float, frames: Iterable[FrameLoad]) -> BusBudget:
    """Bus time of ``frames`` per cycle at ``bitrate`` against ``period_s``, with warnings."""
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
    if nominal_us > period_us:
        warnings.append(
            f"the cyclic CAN traffic needs {nominal_us:.0f} us per cycle at {bitrate} bit/s even "
            f"without bit stuffing: it cannot fit a {period_us:.0f} us period")
    elif worst_us > period_us:
        warnings.append(
            f"the cyclic CAN traffic needs {nominal_us:.0f}-{worst_us:.0f} us per cycle at "
            f"{bitrate} bit/s (no / worst-case bit stuffing): a {period_us:.0f} us period fits "
            f"only if the data stuffs little")
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
    (worst-case bit stuffing): ``max_axes`` axes like the first fit this period, and these
    axes fit periods from ``min_period_us`` on."""

    budget: BusBudget
    axes: tuple[AxisTraffic, ...]
    max_axes: int
    min_period_us: float

    @property
    def fits(self) -> bool:
        return self.budget.fits

    def problem(self) -> str | None:
        """Why the plan does not fit, with the numbers and the ways out (None: it fits)."""
        if self.fits:
            return None
        b, n = self.budget, len(self.axes)
        stuffing = ("even without bit stuffing" if b.nominal_us > b.period_us else
                    f"with worst-case bit stuffing ({b.nominal_us:.0f} us without)")
        ways = [f"a period of at least {self.min_period_us:.0f} us "
                f"({1e6 / self.min_period_us:.0f} Hz)"]
        if self.max_axes >= 1:
            buses = -(-n // self.max_axes)
            fit = "fits" if self.max_axes == 1 else "fit"
            ways.append(f"{buses} buses ({_axes(self.max_axes)} per bus {fit} this period)")
        else:
            ways.append("another bus does not help: one axis alone does not fit this period")
        ways.append("fewer mapped objects (the TPDOs carry "
                    f"{sum(sum(a.tpdo_bytes) for a in self.axes)} bytes per cycle)")
        return (f"{_axes(n)} need{'s' if n == 1 else ''} {b.worst_us:.0f} us of bus time per "
                f"cycle at {b.bitrate} bit/s {stuffing}: more than the {b.period_us:.0f} us "
                f"period; options: {'; '.join(ways)}")

    def summary(self) -> dict[str, float | int | bool | list[str] | str | None]:
        return {**self.budget.summary(), "axes": len(self.axes), "max_axes": self.max_axes,
                "min_period_us": round(self.min_period_us, 1), "problem": self.problem()}


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
             master_heartbeat_s: float = 0.0) -> BusPlan:
    """The plan of ``axes`` sharing one bus at ``bitrate``, cycled every ``period_s``."""
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
    return BusPlan(budget, axes, max_axes, min_period_us)
