"""The master's settings (``[master]`` and ``[bus]`` of drive.toml, read by
:mod:`hil.servo.config`)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DriveMasterConfig:
    """How the master drives one node. ``eds``: the drive's own EDS or DCF, checked before the
    drive is configured (:mod:`hil.drivers.canopen.eds`); None: the objects are checked by SDO.
    ``sync_echo``: the drive's object (index, sub-index; UNSIGNED8) that holds the counter of
    the SYNC its TPDOs answer; the master then turns the SYNC counter on (0x1019) and maps it
    as the last byte of both TPDOs, so every TPDO is bound to its SYNC exactly.
    ``tpdo_layout``: ``"two"`` TPDOs a cycle (statusword and position; velocity and torque),
    or ``"one"`` (statusword, position and torque in 8 bytes; the velocity derived from the
    position: :data:`hil.protocols.cia402.TPDO_LAYOUTS`). ``lockstep_timeout_s``: in lockstep over a
    bus, how long (wall clock) the master waits for the drive's answer to a SYNC or an SDO
    request before it calls the drive gone."""

    node_id: int = 1
    mode: str = "cst"
    cycle_period_s: float = 500e-6
    bitrate: int = 1_000_000
    channel: str = "can0"
    current_limit_ma: float = 1000.0
    heartbeat_id: int = 127
    heartbeat_period_ms: int = 50
    heartbeat_timeout_ms: int = 300
    drive_heartbeat_ms: int = 100
    stale_cycles: int = 20
    rx_timeout_s: float = 400e-6
    sdo_timeout_s: float = 1.0
    state_timeout_s: float = 2.0
    quick_stop_option: int = 2
    quick_stop_timeout_s: float = 3.0
    standstill_deg_s: float = 2.0
    eds: str | None = None
    sync_echo: tuple[int, int] | None = None
    tpdo_layout: str = "two"
    lockstep_timeout_s: float = 10.0
    #: lockstep over a bus: every wait is ``rx_timeout_s`` of wall time (the drive keeps the
    #: master's time, or is paused), and a drive that sends nothing at all for a whole wait
    #: is gone (DriveGoneError), not merely late
    lockstep: bool = False
