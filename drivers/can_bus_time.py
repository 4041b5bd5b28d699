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


def cia402_cyclic_frames(
    period_s: float,
    *,
    rpdo_bytes: int = 4,
    tpdo_bytes: Iterable[int] = (6, 6),
    heartbeat_periods_s: Iterable[float] = (),
) -> list[FrameLoad]:
    """The frames of one drive's cyclic exchange: SYNC, the RPDO, the TPDOs, plus heartbeats
    (one byte each, averaged over the cycle)."""
    frames = [FrameLoad("SYNC", 0), FrameLoad("RPDO1", rpdo_bytes)]
    frames += [FrameLoad(f"TPDO{i}", n) for i, n in enumerate(tpdo_bytes, start=1)]
    for i, hb_period in enumerate(heartbeat_periods_s, start=1):
        if hb_period > 0:
            frames.append(FrameLoad(f"heartbeat{i}", 1, per_cycle=period_s / hb_period))
    return frames
