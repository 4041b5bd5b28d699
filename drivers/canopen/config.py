"""The master's settings (``[master]`` and ``[bus]`` of drive.toml, read by
:mod:`hil.servo.config`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from hil.protocols.cia402 import (
    HOME_OFFSET,
    HOMING_ACCELERATION,
    HOMING_METHOD,
    HOMING_SPEEDS,
    PROFILE_ACCELERATION,
    PROFILE_DECELERATION,
    PROFILE_VELOCITY,
)

#: the configured value of each profile object: (the field of ProfileSettings, its key)
PROFILE_KEYS: dict[tuple[int, int], tuple[str, str]] = {
    (PROFILE_VELOCITY, 0): ("velocity_deg_s", "[profile] velocity_deg_s"),
    (PROFILE_ACCELERATION, 0): ("acceleration_deg_s2", "[profile] acceleration_deg_s2"),
    (PROFILE_DECELERATION, 0): ("deceleration_deg_s2", "[profile] deceleration_deg_s2"),
    (HOMING_METHOD, 0): ("homing_method", "[homing] method"),
    (HOME_OFFSET, 0): ("home_offset_deg", "[homing] offset_deg"),
    (HOMING_SPEEDS, 1): ("homing_switch_speed_deg_s", "[homing] switch_speed_deg_s"),
    (HOMING_SPEEDS, 2): ("homing_zero_speed_deg_s", "[homing] zero_speed_deg_s"),
    (HOMING_ACCELERATION, 0): ("homing_acceleration_deg_s2", "[homing] acceleration_deg_s2"),
}


@dataclass(frozen=True)
class ProfileSettings:
    """How PP and PV move (``[profile]``) and how HM homes (``[homing]``), in hil's units;
    None: the drive's own value, left as it is. ``move_timeout_s``, ``homing_timeout_s``: how
    long a move or a homing may take before the master gives up on it."""

    velocity_deg_s: float | None = None
    acceleration_deg_s2: float | None = None
    deceleration_deg_s2: float | None = None
    homing_method: int | None = None
    home_offset_deg: float | None = None
    homing_switch_speed_deg_s: float | None = None
    homing_zero_speed_deg_s: float | None = None
    homing_acceleration_deg_s2: float | None = None
    move_timeout_s: float = 30.0
    homing_timeout_s: float = 60.0

    def value_of(self, index: int, subindex: int) -> float | None:
        """The configured value of profile object ``index:subindex`` (None: the drive's)."""
        value: float | None = getattr(self, PROFILE_KEYS[index, subindex][0])
        return value


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
    request before it calls the drive gone. ``increments_per_rev``, ``rated_current_ma`` and
    ``max_torque_permille`` stand in for 0x608F:1, 0x6075 and 0x6072 on a drive without them
    (None: not set; a drive that has the object is read). ``profile``: PP's and PV's profile
    and HM's homing."""

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
    increments_per_rev: int | None = None
    rated_current_ma: float | None = None
    max_torque_permille: int | None = None
    profile: ProfileSettings = field(default_factory=ProfileSettings)
