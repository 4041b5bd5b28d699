"""What the master puts on a bus each cycle, and whether several axes fit one bus: the figure
``hil drive plan`` prints and a run on several axes is held to."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

from hil.drivers.can_bus_time import AxisTraffic, BusPlan, plan_bus
from hil.drivers.canopen.config import DriveMasterConfig
from hil.drivers.canopen.pdo import tpdo_maps
from hil.protocols.cia402 import OPERATION_MODES


def axis_traffic(config: DriveMasterConfig, name: str = "axis",
                 layout: str | None = None) -> AxisTraffic:
    """What one node driven with ``config`` puts on the bus each cycle (for bus plans); with
    ``layout``, as if its ``tpdo_layout`` were that one."""
    maps = tpdo_maps(config.sync_echo, layout or config.tpdo_layout)
    return AxisTraffic(name, OPERATION_MODES[config.mode].rpdo1().size_bytes,
                       tuple(pdo.size_bytes for pdo in maps), config.drive_heartbeat_ms / 1e3)


LEAN_LAYOUT = ('master.tpdo_layout = "one" (statusword, position and torque in one 8-byte '
               'TPDO per axis, the velocity derived from the position)')


def plan_axes(config: DriveMasterConfig, names: Sequence[str],
              bitrate: int | None = None) -> BusPlan:
    """The bus plan of the axes ``names`` on one bus, each driven with ``config``, at
    ``bitrate`` (default: the config's): what ``hil drive plan`` prints and what a run on
    several axes is held to, one figure for both. Its ways out name the one-TPDO layout while
    the config maps two."""
    lean: list[AxisTraffic] = []
    how = LEAN_LAYOUT
    if config.tpdo_layout != "one":
        if config.sync_echo is not None:  # the echo byte does not fit the one 8-byte TPDO
            how += ' and sync_echo = ""'
        lean = [axis_traffic(replace(config, sync_echo=None), name, "one") for name in names]
    return plan_bus(bitrate or config.bitrate, config.cycle_period_s,
                    [axis_traffic(config, name) for name in names],
                    master_heartbeat_s=config.heartbeat_period_ms / 1e3, lean=lean,
                    lean_how=how)
