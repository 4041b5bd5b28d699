"""The current a master may send a drive: the smallest of the run's limit and the drive's own,
read before anything is written (a limit only ever tightens on its way to the drive).

* the run's limit: ``current_limit_mA`` of the master's config (lowered by a flag, never raised
  unless the user said so);
* 0x6073 max current and 0x6072 max torque as the drive holds them, per mille of its rated
  current (0x6075; hil reads the torque objects as current), each optional in CiA 402.

The master writes the result to 0x6072 for the session and puts the drive's own value back when
it lets the drive go, so one run's limit never becomes the next one's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hil.drivers.canopen.scaling import DriveScaling, optional_object
from hil.drivers.canopen.sdo import SdoClient
from hil.protocols.cia402 import MAX_CURRENT, MAX_TORQUE


@dataclass(frozen=True)
class CurrentLimit:
    """Each link of the chain [mA] (None: the drive has no such object) and the raw 0x6072
    found, to put back."""

    run_ma: float
    max_current_ma: float | None   # 0x6073
    max_torque_ma: float | None    # 0x6072 as found
    max_torque_found: int | None   # its raw per mille

    @property
    def applied_ma(self) -> float:
        """The smallest link: what the master clamps every command to."""
        return min(v for v in (self.run_ma, self.max_current_ma, self.max_torque_ma)
                   if v is not None)

    def describe(self) -> dict[str, Any]:
        return {"applied_mA": self.applied_ma, "run_mA": self.run_ma,
                "drive_max_current_mA": self.max_current_ma,
                "drive_max_torque_mA": self.max_torque_ma}

    def text(self) -> str:
        """``300 mA: the run's 300 mA, the drive's max current (0x6073) 2000 mA, ...``."""
        links = [f"the run's {self.run_ma:g} mA"]
        for name, value in (("max current (0x6073)", self.max_current_ma),
                            ("max torque (0x6072)", self.max_torque_ma)):
            links.append(f"the drive's {name} " + ("-" if value is None else f"{value:g} mA"))
        return f"{self.applied_ma:g} mA, the smallest of " + ", ".join(links)


def read_current_limit(sdo: SdoClient, scaling: DriveScaling, run_ma: float) -> CurrentLimit:
    """The chain of ``run_ma`` and the drive's 0x6073 / 0x6072, read by SDO."""
    current = optional_object(sdo, MAX_CURRENT, 0, "<H")
    torque = optional_object(sdo, MAX_TORQUE, 0, "<H")
    return CurrentLimit(run_ma, None if current is None else scaling.milliamps(current),
                        None if torque is None else scaling.milliamps(torque), torque)
