"""``drive.toml`` parsed once, strictly, into the frozen settings of the master and the emulator.

The packaged ``hil/configs/drive.toml`` holds every key with its default; a user file is laid
over it table by table, then overrides (command-line flags, tests). Every key is read with its
type and range through :class:`hil.core.config.Table`: an unknown key, a wrong type or a value
out of range is one :class:`~hil.core.errors.ConfigError` naming the file and the dotted key.
The driver (:class:`~drivers.canopen.config.DriveMasterConfig`, the bus as a
:class:`~drivers.canopen.bus.CanBusSpec`) and the emulator
(:class:`~emulators.drive.node.DriveEmulatorConfig`) define their settings and never read TOML.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from typing import Any

from drivers.canopen.bus import SOCKETCAND, CanBusSpec
from drivers.canopen.config import DriveMasterConfig
from drivers.cia402 import MODES, QUICK_STOP_OPTIONS
from emulators.drive.config import DriveEmulatorConfig
from emulators.drive.plant import Disturbance, Friction
from hil.core.config import Table, deep_merge, load_toml, parse_toml
from hil.core.errors import ConfigError
from hil.core.verdict import RunTables, read_run_tables
from hil.servo.safety import ServoSafety

AXIS_NAME = re.compile(r"[a-z][a-z0-9_]{0,15}")
DEFAULT_SOURCE = "hil/configs/drive.toml"
SOURCE = "drive config"  # what errors name when no user file is given
U16 = 0xFFFF
EMULATED = "emulated"


@dataclass(frozen=True)
class AxisSpec:
    """One axis of a run on several axes: its name (topics, KPIs) and its drive's node id."""

    name: str
    node: int


def check_axes(axes: tuple[AxisSpec, ...], where: str) -> tuple[AxisSpec, ...]:
    """Two axes or more, names and node ids each once (ConfigError naming ``where``)."""
    if len(axes) < 2:
        raise ConfigError(f"{where}: name two axes or more (one axis: the master's node_id)")
    for what, values in (("name", [a.name for a in axes]), ("node", [a.node for a in axes])):
        if len(set(values)) != len(values):
            raise ConfigError(f"{where}: a {what} given twice")
    return axes


@dataclass(frozen=True)
class DriveConfig:
    """drive.toml as read: the master's and the emulator's settings, and what a session
    records of it (the merged tables and the text of the user's file, or of the default)."""

    master: DriveMasterConfig
    emulator: DriveEmulatorConfig
    bus: CanBusSpec | None       # [bus]: the drive's bus; None: the emulated drive
    safety: ServoSafety          # [safety]: the run's safety limits
    data: Mapping[str, Any]
    text: str
    source: str
    run: RunTables               # [controller] params and [limits] of a run
    axes: tuple[AxisSpec, ...] = ()  # [[axis]]: several axes on the bus (none: one)

    @property
    def bus_url(self) -> str:
        """``[bus]`` as a drive URL (``emulated`` for the emulated drive)."""
        return self.bus.url if self.bus is not None else EMULATED

    def laid_over(self, overrides: Mapping[str, Any]) -> DriveConfig:
        """These settings with ``overrides`` laid over them (checked again)."""
        return parse_drive_config(deep_merge(self.data, overrides), self.source, self.text)


def default_drive_text() -> str:
    """The packaged default drive config (TOML text, with its comments)."""
    return resources.files("hil.configs").joinpath("drive.toml").read_text("utf-8")


def load_drive_config(path: str | os.PathLike[str] | None = None,
                      overrides: Mapping[str, Any] | None = None) -> DriveConfig:
    """The packaged default, the file at ``path`` laid over it, then ``overrides`` (e.g.
    ``{"master": {"current_limit_mA": 12000.0}}``), parsed."""
    text = default_drive_text()
    data = parse_toml(text, DEFAULT_SOURCE)
    if path is not None:
        user, text = load_toml(path)
        data = deep_merge(data, user)
    source = os.fspath(path) if path is not None else SOURCE
    return parse_drive_config(deep_merge(data, overrides or {}), source, text)


def parse_drive_config(data: Mapping[str, Any], source: str, text: str = "") -> DriveConfig:
    """Complete drive tables (the default's keys all present) -> :class:`DriveConfig`."""
    root = Table(data, source)
    bus_table = root.table("bus", required=True)
    bus = _bus(bus_table)
    master = _master(root.table("master", required=True), bus_table)
    emulator = _emulator(root.table("emulator", required=True))
    safety = _safety(root.table("safety", required=True))
    run = read_run_tables(root)
    axes = _axes(root)
    root.done()
    return DriveConfig(master=master, emulator=emulator, bus=bus, safety=safety, data=data,
                       text=text, source=source, run=run, axes=axes)


def _axes(root: Table) -> tuple[AxisSpec, ...]:
    """``[[axis]]`` tables: ``name`` and ``node`` each."""
    tables = root.raw("axis", [])
    if not isinstance(tables, list):
        raise root.error("axis", "must be an array of tables ([[axis]])")
    axes = []
    for i, data in enumerate(tables):
        table = Table(data, root.source, f"axis[{i}]")
        name = table.string("name")
        if not AXIS_NAME.fullmatch(name):
            raise table.error("name", f"must be a lower-case name (a-z, 0-9, _), got {name!r}")
        axes.append(AxisSpec(name, table.integer("node", at_least=1, at_most=127)))
        table.done()
    return check_axes(tuple(axes), f"{root.source}: [[axis]]") if axes else ()


def _safety(s: Table) -> ServoSafety:
    """``[safety]``: every limit positive, the position range ordered."""
    safety = ServoSafety(
        enabled=s.boolean("enabled"),
        following_error_deg=s.number("following_error_deg", above=0),
        following_error_ms=s.number("following_error_ms", at_least=0, at_most=60_000),
        position_min_deg=s.number("position_min_deg"),
        position_max_deg=s.number("position_max_deg"),
        velocity_max_deg_s=s.number("velocity_max_deg_s", above=0),
        stale_share_max=s.number("stale_share_max", at_least=0, at_most=1),
        stale_window_ms=s.number("stale_window_ms", above=0, at_most=60_000),
    )
    if not safety.position_min_deg < safety.position_max_deg:
        raise s.error("position_max_deg", f"must be above position_min_deg "
                      f"({safety.position_min_deg:g}), got {safety.position_max_deg:g}")
    s.done()
    return safety


def _bus(bus: Table) -> CanBusSpec | None:
    """``[bus]``: ``interface`` (``emulated``, ``socketcand`` or a python-can interface),
    ``channel`` and ``options`` (keyword arguments of ``can.Bus``; socketcand: host, port)."""
    from can.interfaces import VALID_INTERFACES

    interface = bus.string("interface")
    table = bus.table("options")
    if interface == EMULATED:
        if table.names():
            raise table.error(table.names()[0], "is an option of a CAN interface; "
                              "interface = 'emulated' takes none")
        return None
    if interface not in VALID_INTERFACES:
        raise bus.error("interface", f"must be 'emulated' or a python-can interface "
                        f"({', '.join(sorted(VALID_INTERFACES))}), got {interface!r}")
    options = {name: table.raw(name) for name in table.names()}
    table.done()
    if interface == SOCKETCAND and not ({"host", "port"} <= set(options)):
        raise bus.error("options", "socketcand needs host and port, e.g. "
                        "options = { host = '192.168.0.60', port = 29536 }")
    return CanBusSpec(interface, bus.string("channel"), options)


def _quick_stop_option(table: Table) -> int:
    option = table.integer("quick_stop_option")
    if option not in QUICK_STOP_OPTIONS:
        raise table.error("quick_stop_option", f"must be one of "
                          f"{', '.join(map(str, QUICK_STOP_OPTIONS))}, got {option}")
    return option


def _master(m: Table, bus: Table) -> DriveMasterConfig:
    """``[master]`` and ``[bus]``."""
    channel = bus.string("channel")
    if not channel:
        raise bus.error("channel", "must be a bus name, got ''")
    config = DriveMasterConfig(
        node_id=m.integer("node_id", at_least=1, at_most=127),
        mode=m.string("mode", choices=tuple(MODES)),
        cycle_period_s=m.integer("cycle_period_us", above=0) / 1e6,
        bitrate=bus.integer("bitrate", above=0),
        channel=channel,
        current_limit_ma=m.number("current_limit_mA", above=0, at_most=32_767),
        heartbeat_id=m.integer("heartbeat_id", at_least=1, at_most=127),
        heartbeat_period_ms=m.integer("heartbeat_period_ms", at_least=0, at_most=U16),
        heartbeat_timeout_ms=m.integer("heartbeat_timeout_ms", at_least=0, at_most=U16),
        drive_heartbeat_ms=m.integer("drive_heartbeat_ms", at_least=0, at_most=U16),
        stale_cycles=m.integer("stale_cycles", above=0),
        rx_timeout_s=m.integer("rx_timeout_us", above=0) / 1e6,
        sdo_timeout_s=m.integer("sdo_timeout_ms", above=0) / 1e3,
        state_timeout_s=m.integer("state_timeout_ms", above=0) / 1e3,
        quick_stop_option=_quick_stop_option(m),
        quick_stop_timeout_s=m.integer("quick_stop_timeout_ms", above=0) / 1e3,
        standstill_deg_s=m.number("standstill_deg_s", above=0),
        eds=m.string("eds") or None,
        sync_echo=_object_address(m, "sync_echo"),
    )
    m.done()
    bus.done()
    return config


def _object_address(table: Table, name: str) -> tuple[int, int] | None:
    """``"0x2004"`` or ``"0x2004:0"`` -> (0x2004, 0); ``""`` -> None."""
    text = table.string(name).strip()
    if not text:
        return None
    index, _, sub = text.partition(":")
    try:
        address = int(index, 0), int(sub or "0", 0)
    except ValueError:
        address = (-1, -1)
    if not (0x1000 <= address[0] <= 0xFFFF and 0 <= address[1] <= 0xFF):
        raise table.error(name, f"must be an object as INDEX[:SUBINDEX], e.g. '0x2004:0', "
                          f"got {text!r}")
    return address


def _or_inf(value: float | None) -> float:
    return math.inf if value is None else value


def _emulator(e: Table) -> DriveEmulatorConfig:
    """``[emulator]`` with its ``friction`` and ``disturbance`` sub-tables."""
    f, d = e.table("friction"), e.table("disturbance")
    friction = Friction(
        viscous_ma_per_deg_s=f.number("viscous_mA_per_deg_s"),
        coulomb_ma=f.number("coulomb_mA"),
        coulomb_smoothing_deg_s=f.number("coulomb_smoothing_deg_s", above=0),
    )
    disturbance = Disturbance(
        constant_ma=d.number("constant_mA"),
        start_s=d.number("start_s"),
        end_s=_or_inf(d.number("end_s", None)),
        sine_ma=d.number("sine_mA"),
        sine_hz=d.number("sine_hz"),
    )
    config = DriveEmulatorConfig(
        node_id=e.integer("node_id", at_least=1, at_most=127),
        rated_current_ma=e.integer("rated_current_mA", above=0),
        max_torque_permille=e.integer("max_torque_permille", at_least=0, at_most=U16),
        current_limit_ma=e.number("current_limit_mA", above=0),
        overcurrent_trip_ma=e.integer("overcurrent_trip_mA", above=0, at_most=U16),
        increments_per_rev=e.integer("increments_per_rev", at_least=2, at_most=2**31 - 1),
        heartbeat_ms=e.integer("heartbeat_ms", at_least=0, at_most=U16),
        sync_loss_timeout_ms=e.integer("sync_loss_timeout_ms", at_least=0, at_most=U16),
        quick_stop_option=_quick_stop_option(e),
        quick_stop_timeout_ms=e.integer("quick_stop_timeout_ms", above=0),
        standstill_deg_s=e.number("standstill_deg_s", above=0),
        velocity_gain_ma_per_deg_s=e.number("velocity_gain_mA_per_deg_s", above=0),
        position_gain_per_s=e.number("position_gain_per_s", above=0),
        channel=e.string("channel"),
        friction=friction,
        disturbance=disturbance,
    )
    for table in (f, d, e):
        table.done()
    return config
