"""What the emulated drive is given (``[emulator]`` of drive.toml, read by
:mod:`hil.servo.config`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from hil.controllers.servo.model import SAMPLE_PERIOD_S
from hil.emulators.drive.axis_model import AxisModel
from hil.emulators.drive.od import OdDefaults
from hil.emulators.drive.plant import AxisPlant, Disturbance, Friction
from hil.emulators.drive.switches import Switches
from hil.emulators.faults import Fault


@dataclass(frozen=True)
class DriveEmulatorConfig:
    """Everything the emulated drive needs (``[emulator]`` of drive.toml, read by
    :mod:`hil.servo.config`)."""

    node_id: int = 1
    eds: str | None = None  # the drive's EDS or DCF: a twin of it (emulators/drive/twin.py)
    # the object dictionary's start-up values are the defaults (emulators/drive/od.py)
    rated_current_ma: int = OdDefaults.rated_current_ma
    max_torque_permille: int = OdDefaults.max_torque_permille
    current_limit_ma: float = 12_000.0
    overcurrent_trip_ma: int = OdDefaults.overcurrent_trip_ma
    increments_per_rev: int = OdDefaults.increments_per_rev
    heartbeat_ms: int = OdDefaults.heartbeat_ms
    sync_loss_timeout_ms: int = OdDefaults.sync_loss_timeout_ms
    quick_stop_option: int = OdDefaults.quick_stop_option
    quick_stop_timeout_ms: int = 3000
    standstill_deg_s: float = 2.0
    velocity_gain_ma_per_deg_s: float = 40.0
    position_gain_per_s: float = 20.0
    channel: str = "can0"
    friction: Friction = field(default_factory=Friction)
    disturbance: Disturbance = field(default_factory=Disturbance)
    switches: Switches = field(default_factory=Switches)  # limit and home switches, index
    homing_search_deg: float = 720.0  # a homing that finds nothing this far away: error
    #: power-on values of objects ((index, subindex), value): ``[emulator] set``, ``--set``
    object_values: tuple[tuple[tuple[int, int], int], ...] = ()
    axis_model: AxisModel | None = None  # a model file's axis (None: the published axis)
    faults: tuple[Fault, ...] = ()  # [emulator] faults: what it does wrong, and when

    def od_defaults(self) -> OdDefaults:
        return OdDefaults(
            rated_current_ma=self.rated_current_ma, max_torque_permille=self.max_torque_permille,
            increments_per_rev=self.increments_per_rev, heartbeat_ms=self.heartbeat_ms,
            sync_loss_timeout_ms=self.sync_loss_timeout_ms,
            overcurrent_trip_ma=self.overcurrent_trip_ma, quick_stop_option=self.quick_stop_option,
        )

    @property
    def axis_period_s(self) -> float:
        """The axis' model period [s]: the drive steps it cycle / period times per SYNC."""
        return self.axis_model.dt if self.axis_model is not None else SAMPLE_PERIOD_S

    def make_plant(self) -> AxisPlant:
        return AxisPlant(self.axis_model, current_limit_ma=self.current_limit_ma,
                         increments_per_rev=self.increments_per_rev,
                         friction=self.friction, disturbance=self.disturbance)
