"""``drive.toml`` parsed once, strictly, into the frozen settings of the master and the emulator.

The packaged ``hil/configs/drive.toml`` holds every key with its default; a user file is laid
over it table by table, then overrides (command-line flags, tests). Every key is read with its
type and range through :class:`hil.core.config.Table`: an unknown key, a wrong type or a value
out of range is one :class:`~hil.errors.ConfigError` naming the file and the dotted key.
The driver (:class:`~hil.drivers.canopen.config.DriveMasterConfig`, the bus as a
:class:`~hil.drivers.canopen.bus.CanBusSpec`) and the emulator
(:class:`~hil.emulators.drive.node.DriveEmulatorConfig`) define their settings and never read TOML.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from importlib import resources
from typing import Any

from can.interfaces import VALID_INTERFACES

from hil.core.config import Table, load_toml, parse_toml
from hil.core.ranges import PLAUSIBLE_MILLIAMPS
from hil.core.registry import scheme_of
from hil.core.settings import KeyRead, Layer, Layered, Setting, effective, lay
from hil.core.verdict import RunTables, read_run_tables
from hil.drivers.can_bus_time import CAN_FD_MAX_BITRATE, CLASSIC_CAN_MAX_BITRATE, max_bitrate
from hil.drivers.canopen.bus import SOCKETCAND, CanBusSpec, parse_can_url
from hil.drivers.canopen.config import DriveMasterConfig, ProfileSettings
from hil.emulators.drive.axis_model import AxisModel, load_axis_model, period_problem
from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.plant import Disturbance, Friction
from hil.emulators.drive.switches import Switches
from hil.emulators.errors import EmulatorSetupError
from hil.emulators.faults import Fault, for_emulator, parse_faults_table
from hil.errors import ConfigError, UsageError
from hil.protocols.cia402 import OPERATION_MODES, QUICK_STOP_OPTIONS, TPDO_LAYOUTS
from hil.servo.safety import ServoSafety

AXIS_NAME = re.compile(r"[a-z][a-z0-9_]{0,15}")
DEFAULT_SOURCE = "hil/configs/drive.toml"
SOURCE = "drive config"  # what errors name when no user file is given
U16 = 0xFFFF
U32 = 0xFFFF_FFFF
EMULATED = "emulated"


@dataclass(frozen=True)
class AxisSpec:
    """One axis of a run: its name (topics, KPIs), its drive's node id, its own current limit
    (None: the master's; the smaller of the two holds), its bus, its drive's EDS (None: the
    master's) and its own safety limits (:func:`stricter_safety`: the stricter of them and the
    run's ``[safety]`` hold)."""

    name: str
    node: int
    current_limit_ma: float | None = None
    bus: str = ""  # its bus's URL ("": the run's, --drive or [bus])
    eds: str | None = None
    safety: Mapping[str, Any] = field(default_factory=dict)  # [axis.safety] keys given

    def master(self, master: DriveMasterConfig) -> DriveMasterConfig:
        """``master`` for this axis' drive: its node id, its current limit if tighter, its
        EDS if it has one."""
        limit = master.current_limit_ma if self.current_limit_ma is None \
            else min(master.current_limit_ma, self.current_limit_ma)
        return replace(master, node_id=self.node, current_limit_ma=limit,
                       eds=self.eds or master.eds)


#: how each ``[safety]`` key is made stricter: the smaller or the larger of two values
STRICTER = {"following_error_deg": min, "following_error_ms": min, "position_min_deg": max,
            "position_max_deg": min, "velocity_max_deg_s": min, "stale_share_max": min,
            "stale_window_ms": min}


def stricter_safety(run: ServoSafety, axis: Mapping[str, Any]) -> ServoSafety:
    """The run's ``[safety]`` with an axis' own limits where they are stricter: an axis can
    tighten a limit for itself, never loosen one (``enabled`` holds when either says so)."""
    values = {key: pick(getattr(run, key), axis[key])
              for key, pick in STRICTER.items() if key in axis}
    if "enabled" in axis:
        values["enabled"] = run.enabled or bool(axis["enabled"])
    return replace(run, **values)


def check_axes(axes: tuple[AxisSpec, ...], where: str) -> tuple[AxisSpec, ...]:
    """Two axes or more, names each once, node ids each once on a bus (ConfigError naming
    ``where``)."""
    if len(axes) < 2:
        raise ConfigError(f"{where}: name two axes or more (one axis: the master's node_id)")
    names = [a.name for a in axes]
    if len(set(names)) != len(names):
        raise ConfigError(f"{where}: a name given twice")
    nodes = [(a.bus, a.node) for a in axes]
    for bus, node in nodes:
        if nodes.count((bus, node)) > 1:
            raise ConfigError(f"{where}: a node given twice on {bus or 'one bus'} "
                              f"(node {node})")
    return axes


def bitrate_problem(bitrate: int, fd: bool) -> str | None:
    """Why a bus cannot run at ``bitrate`` bit/s (``fd``: a CAN FD bus); None: it can."""
    if bitrate <= max_bitrate(fd):
        return None
    if fd:
        return f"CAN FD stops at {CAN_FD_MAX_BITRATE} bit/s"
    return (f"classic CAN stops at {CLASSIC_CAN_MAX_BITRATE} bit/s (1 Mbit/s); above it only "
            "on a CAN FD bus: fd = true in [bus.options] (or ?fd=true in a bus URL)")


def check_bitrate(bitrate: int, fd: bool, what: str) -> None:
    """``bitrate`` bit/s on a bus (``fd``: CAN FD) given by ``what`` (a flag, a URL): a
    UsageError naming it and the unit when the bus cannot run at it."""
    problem = bitrate_problem(bitrate, fd)
    if problem is not None:
        raise UsageError(f"{what} {bitrate} bit/s: {problem}")


@dataclass(frozen=True)
class DriveConfig:
    """drive.toml as read: the master's and the emulator's settings, and what a session
    records of it (the layers it was laid from, the text of the user's file, or of the
    default, and every key as read)."""

    master: DriveMasterConfig
    emulator: DriveEmulatorConfig
    bus: CanBusSpec | None       # [bus]: the drive's bus; None: the emulated drive
    safety: ServoSafety          # [safety]: the run's safety limits
    layered: Layered             # the layers and the merged tables
    text: str
    source: str
    run: RunTables               # [controller] params and [limits] of a run
    axes: tuple[AxisSpec, ...] = ()  # [[axis]]: several axes on the bus (none: one)
    reads: tuple[KeyRead, ...] = ()  # every key as read, in reading order
    url: str = ""                # [bus] url: the bus as one URL ("": interface, channel...)

    @property
    def data(self) -> dict[str, Any]:
        """The merged tables (what a session records as the drive config)."""
        return self.layered.data

    @property
    def bus_url(self) -> str:
        """``[bus]`` as a drive URL: its ``url``, else its interface, channel and options
        (``emulated`` for the emulated drive)."""
        return self.url or (self.bus.url if self.bus is not None else EMULATED)

    def settings(self) -> list[Setting]:
        """Every key as it runs, with its origin."""
        return effective(self.reads, self.layered)

    def laid_over(self, overrides: Mapping[str, Any], origin: str = "overrides",
                  whole: tuple[str, ...] = ()) -> DriveConfig:
        """These settings with ``overrides`` laid over them as a layer named ``origin``
        (checked again)."""
        layered = self.layered.with_layer(Layer(origin, overrides, whole))
        return parse_drive_config(layered, self.source, self.text)


def default_drive_text() -> str:
    """The packaged default drive config (TOML text, with its comments)."""
    return resources.files("hil.configs").joinpath("drive.toml").read_text("utf-8")


def drive_layers(path: str | os.PathLike[str] | None = None) -> tuple[list[Layer], str]:
    """The packaged default and the user's file at ``path`` over it, as layers; and the text a
    session attaches (the user's file, else the default)."""
    text = default_drive_text()
    packaged = str(resources.files("hil.configs"))
    layers = [Layer(DEFAULT_SOURCE, parse_toml(text, DEFAULT_SOURCE), folder=packaged)]
    if path is not None:
        user, text = load_toml(path)
        path = os.fspath(path)
        layers.append(Layer(f"--config {path}", user,
                            folder=os.path.dirname(os.path.abspath(path))))
    return layers, text


def drive_for(limit_ma: float) -> dict[str, Any]:
    """The drive configured for a case's current (the paper's rated 12 A at 10 Hz): the
    master's limit, and the emulated drive's own max torque 0x6072 (per mille of its rated
    1000 mA), which no master goes above."""
    return {"master": {"current_limit_mA": limit_ma},
            "emulator": {"max_torque_permille": max(1000, round(limit_ma))}}


def load_drive_config(path: str | os.PathLike[str] | None = None,
                      overrides: Mapping[str, Any] | None = None,
                      origin: str = "overrides") -> DriveConfig:
    """The packaged default, the file at ``path`` laid over it, then ``overrides`` (e.g.
    ``{"master": {"current_limit_mA": 12000.0}}``, a layer named ``origin``), parsed."""
    layers, text = drive_layers(path)
    if overrides:
        layers.append(Layer(origin, overrides))
    source = os.fspath(path) if path is not None else SOURCE
    return parse_drive_config(lay(layers), source, text)


def parse_drive_config(layered: Layered, source: str, text: str = "") -> DriveConfig:
    """Complete drive tables (the default's keys all present) -> :class:`DriveConfig`."""
    root = Table(layered.data, source, layered=layered)
    bus_table = root.table("bus", required=True)
    url = _bus_url(bus_table)
    bus = _bus(bus_table, url)
    fd = bus is not None and bus.options.get("fd") is True
    profile = _profile(root.table("profile", required=True),
                       root.table("homing", required=True))
    master = _master(root.table("master", required=True), bus_table, profile, fd)
    emulator = _emulator(root.table("emulator", required=True), master.cycle_period_s)
    if emulator.eds is not None:  # resolved in the tables too: an emulator process reads them
        layered.data["emulator"]["eds"] = emulator.eds  # from a file of its own, elsewhere
    safety = _safety(root.table("safety", required=True))
    run = read_run_tables(root)
    axes = _axes(root)
    root.done()
    return DriveConfig(master=master, emulator=emulator, bus=bus, safety=safety,
                       layered=layered, text=text, source=source, run=run, axes=axes,
                       reads=tuple(root.reads), url=url)


def _axes(root: Table) -> tuple[AxisSpec, ...]:
    """``[[axis]]`` tables: ``name`` and ``node`` each, optionally ``current_limit_mA``,
    ``bus`` (its bus's URL; "": the run's), ``eds`` (its drive's EDS or DCF) and a ``safety``
    table (any keys of ``[safety]``, checked as they are)."""
    tables = root.value("axis", [], kind="array of tables")
    if not isinstance(tables, list):
        raise root.error("axis", "must be an array of tables ([[axis]])")
    axes = []
    for i, data in enumerate(tables):
        table = Table(data, root.source, f"axis[{i}]", root.reads, root.layered)
        name = table.string("name")
        if not AXIS_NAME.fullmatch(name):
            raise table.error("name", f"must be a lower-case name (a-z, 0-9, _), got {name!r}")
        axes.append(AxisSpec(name, table.integer("node", at_least=1, at_most=127),
                             table.number("current_limit_mA", None, above=0, at_most=32_767,
                                          plausible=PLAUSIBLE_MILLIAMPS),
                             _axis_bus(table), table.file_path("eds", "") or None,
                             _axis_safety(table.table("safety"))))
        table.done()
    return check_axes(tuple(axes), f"{root.source}: [[axis]]") if axes else ()


def _axis_safety(s: Table) -> dict[str, Any]:
    """An axis' ``safety`` table: the keys it gives, each checked as ``[safety]`` checks it."""
    given = s.names()
    # checked whole, the run's defaults filling what the axis leaves out (not settings of it)
    full = Table({**vars(ServoSafety()), **s.data}, s.source, s.path, [], s.layered)
    checked = vars(_safety(full))
    return {key: checked[key] for key in given}


def _axis_bus(table: Table) -> str:
    """An axis' ``bus``: "" (the run's), ``emulated`` or a bus URL, checked as a run opens
    it (a plug-in's scheme is its own to check)."""
    url = table.string("bus", "").strip()
    if url and scheme_of(url) in VALID_INTERFACES:
        try:
            parse_can_url(url)
        except ConfigError as exc:
            raise table.error("bus", f"is not a bus URL: {exc}") from None
    return url


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


def _bus_url(bus: Table) -> str:
    """``[bus] url``: the bus as one URL, as ``--drive`` takes it (``''``: none), checked as a
    run opens it (a plug-in's scheme is its own to check)."""
    url = bus.string("url").strip()
    if url.startswith(EMULATED + "?"):
        raise bus.error("url", f"is {url!r}: in a config file the emulated drive's axis model "
                        "is [emulator] model; url = 'emulated'")
    if url and scheme_of(url) in VALID_INTERFACES:
        try:
            parse_can_url(url)
        except ConfigError as exc:
            raise bus.error("url", f"is not a bus URL: {exc}") from None
    return url


def _bus(bus: Table, url: str = "") -> CanBusSpec | None:
    """``[bus]``: ``interface`` (``emulated``, ``socketcand`` or a python-can interface),
    ``channel`` and ``options`` (keyword arguments of ``can.Bus``; socketcand: host, port);
    a python-can ``url`` names the bus instead (the others are read, unused)."""
    interface = bus.string("interface")
    table = bus.table("options")
    if url:
        for name in table.names():
            table.value(name)
        table.done()
        return parse_can_url(url) if scheme_of(url) in VALID_INTERFACES else None
    if interface == EMULATED:
        if table.names():
            raise table.error(table.names()[0], "is an option of a CAN interface; "
                              "interface = 'emulated' takes none")
        return None
    if interface not in VALID_INTERFACES:
        raise bus.error("interface", f"must be 'emulated' or a python-can interface "
                        f"({', '.join(sorted(VALID_INTERFACES))}), got {interface!r}")
    options = {name: table.value(name) for name in table.names()}
    table.done()
    if interface == SOCKETCAND and not ({"host", "port"} <= set(options)):
        raise bus.error("options", "socketcand needs host and port, e.g. "
                        "options = { host = '192.168.0.60', port = 29536 }")
    return CanBusSpec(interface, bus.string("channel"), options)


def _quick_stop_option(table: Table) -> int:
    return table.integer("quick_stop_option", choices=tuple(QUICK_STOP_OPTIONS))


def _bitrate(bus: Table, fd: bool) -> int:
    """``[bus] bitrate``: classic CAN's 1 Mbit/s at most, CAN FD's above (``fd``)."""
    value = bus.data.get("bitrate")
    if isinstance(value, int) and not isinstance(value, bool):
        problem = bitrate_problem(value, fd)
        if problem is not None:  # said with the way out, before the range check's words
            raise bus.error("bitrate", f"is {value} bit/s: {problem}")
    return bus.integer("bitrate", above=0, at_most=max_bitrate(fd))


def _tpdo_layout(m: Table, sync_echo: tuple[int, int] | None) -> str:
    """``[master] tpdo_layout``: the one-TPDO layout fills its 8 bytes, so no echo with it."""
    layout = m.string("tpdo_layout", choices=tuple(TPDO_LAYOUTS))
    if layout == "one" and sync_echo is not None:
        raise m.error("tpdo_layout", "= 'one' fills its TPDO's 8 bytes (statusword, position, "
                      "torque): no room for sync_echo; set sync_echo = '' or tpdo_layout = "
                      "'two'")
    return layout


def _profile(p: Table, h: Table) -> ProfileSettings:
    """``[profile]`` (PP's and PV's) and ``[homing]`` (HM's): a key left out keeps the
    drive's own value."""
    profile = ProfileSettings(
        velocity_deg_s=p.number("velocity_deg_s", None, above=0),
        acceleration_deg_s2=p.number("acceleration_deg_s2", None, above=0),
        deceleration_deg_s2=p.number("deceleration_deg_s2", None, above=0),
        move_timeout_s=p.number("timeout_s", above=0, at_most=3600),
        homing_method=h.integer("method", None, at_least=-128, at_most=127),
        home_offset_deg=h.number("offset_deg", None),
        homing_switch_speed_deg_s=h.number("switch_speed_deg_s", None, above=0),
        homing_zero_speed_deg_s=h.number("zero_speed_deg_s", None, above=0),
        homing_acceleration_deg_s2=h.number("acceleration_deg_s2", None, above=0),
        homing_timeout_s=h.number("timeout_s", above=0, at_most=3600),
    )
    p.done()
    h.done()
    return profile


def _master(m: Table, bus: Table, profile: ProfileSettings, fd: bool = False
            ) -> DriveMasterConfig:
    """``[master]`` and ``[bus]`` (``fd``: its options make it a CAN FD bus), with the
    profile and homing of ``profile``."""
    channel = bus.string("channel")
    if not channel:
        raise bus.error("channel", "must be a bus name, got ''")
    config = DriveMasterConfig(
        node_id=m.integer("node_id", at_least=1, at_most=127),
        mode=m.string("mode", choices=tuple(OPERATION_MODES)),
        cycle_period_s=m.integer("cycle_period_us", above=0, at_most=U32) / 1e6,  # 0x1006
        bitrate=_bitrate(bus, fd),
        channel=channel,
        current_limit_ma=m.number("current_limit_mA", above=0, at_most=32_767,
                                  plausible=PLAUSIBLE_MILLIAMPS),
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
        eds=m.file_path("eds") or None,
        sync_echo=(echo := _object_address(m, "sync_echo")),
        tpdo_layout=_tpdo_layout(m, echo),
        lockstep_timeout_s=m.integer("lockstep_timeout_ms", at_least=10, at_most=3_600_000)
        / 1e3,
        increments_per_rev=m.integer("increments_per_rev", None, at_least=1,
                                     at_most=2**31 - 1),
        rated_current_ma=m.number("rated_current_mA", None, above=0),
        max_torque_permille=m.integer("max_torque_permille", None, at_least=1, at_most=U16),
        profile=profile,
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


def parse_object_values(values: Mapping[str, Any], where: str
                        ) -> tuple[tuple[tuple[int, int], int], ...]:
    """``{"0x6075:0" = 2000}`` (``[emulator] set``, ``--set``) -> (((0x6075, 0), 2000),);
    a ConfigError naming ``where`` for a key that is no object or a value that is no
    integer."""
    out = []
    for name, value in values.items():
        index, _, sub = str(name).partition(":")
        try:
            key = int(index, 0), int(sub or "0", 0)
        except ValueError:
            key = (-1, -1)
        if not (0x1000 <= key[0] <= 0xFFFF and 0 <= key[1] <= 0xFF):
            raise ConfigError(f"{where}: {name!r} is no object: give INDEX:SUBINDEX, e.g. "
                              "'0x6075:0'")
        if not isinstance(value, int) or isinstance(value, bool):
            raise ConfigError(f"{where}: {name} = {value!r}: an object's value is an integer")
        out.append((key, value))
    return tuple(out)


def _object_values(e: Table) -> tuple[tuple[tuple[int, int], int], ...]:
    """``[emulator] set``: objects' power-on values, ``{"0x6075:0" = 2000}``."""
    values = e.value("set", kind="table")
    if not isinstance(values, Mapping):
        raise e.error("set", "must be a table of objects' values, e.g. {\"0x6075:0\" = 2000}")
    return parse_object_values(values, f"{e.source}: key '{e.key('set')}'")


def _switches(e: Table) -> Switches:
    """``[emulator]``'s limit switches, home switch and index pulse [deg of the axis]."""
    switches = Switches(
        negative_limit_deg=e.number("negative_limit_deg"),
        positive_limit_deg=e.number("positive_limit_deg"),
        home_switch_deg=e.number("home_switch_deg"),
        index_pulse_deg=e.number("index_pulse_deg", at_least=-360, at_most=360),
    )
    if not switches.negative_limit_deg < switches.positive_limit_deg:
        raise e.error("negative_limit_deg", f"must be below positive_limit_deg "
                      f"({switches.positive_limit_deg:g} deg), got "
                      f"{switches.negative_limit_deg:g} deg")
    return switches


def _or_inf(value: float | None) -> float:
    return math.inf if value is None else value


#: ``[emulator]`` keys that set an object's power-on value, which a twin's EDS gives instead
EDS_OBJECT_KEYS = {"rated_current_mA": "0x6075", "max_torque_permille": "0x6072",
                   "increments_per_rev": "0x608F", "heartbeat_ms": "0x1017",
                   "quick_stop_option": "0x605A"}


def _twin_keys(e: Table, config: DriveEmulatorConfig) -> None:
    """With ``eds`` the EDS gives the objects' power-on values: a key of one of them set to
    another value than hil's default is refused (it could not take effect)."""
    if config.eds is None:
        return
    default = DriveEmulatorConfig()
    for key, index in EDS_OBJECT_KEYS.items():
        field_name = key.replace("_mA", "_ma")
        if getattr(config, field_name) != getattr(default, field_name):
            raise e.error(key, f"is set, and so is eds ({config.eds}): the EDS gives "
                          f"{index}'s power-on value; drop one of the two")


def _axis_model(e: Table, cycle_period_s: float) -> AxisModel | None:
    """``[emulator] model``: a model file's axis (its path from the folder of the config file
    that names it), checked, its period dividing the drive's cycle; '' (None): the published
    axis."""
    path = e.file_path("model")
    if not path:
        return None
    try:
        model = load_axis_model(path)
    except EmulatorSetupError as exc:
        raise e.error("model", f"is no axis model: {exc}") from None
    problem = period_problem(model, cycle_period_s)
    if problem is not None:
        raise e.error("model", f"({path}) does not fit master.cycle_period_us: {problem}")
    return model


def _faults(e: Table) -> tuple[Fault, ...]:
    """``[emulator] faults``: the drive's fault schedule (docs/FAULTS.md), checked."""
    schedule = e.array("faults", [], "faults KIND@START[-END][:KEY=VALUE,...] or inline "
                       "tables (docs/FAULTS.md), drive kinds")
    where = f"{e.source}: emulator"
    return tuple(for_emulator(parse_faults_table({"schedule": schedule}, where), "drive",
                              f"{where}.faults"))


def _emulator(e: Table, cycle_period_s: float) -> DriveEmulatorConfig:
    """``[emulator]`` with its ``friction`` and ``disturbance`` sub-tables; its ``model`` checked
    against the drive's cycle of ``cycle_period_s``."""
    f, d = e.table("friction"), e.table("disturbance")
    friction = Friction(
        viscous_ma_per_deg_s=f.number("viscous_mA_per_deg_s", at_least=0),  # < 0 drives it
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
        eds=e.file_path("eds") or None,
        rated_current_ma=e.integer("rated_current_mA", above=0),
        max_torque_permille=e.integer("max_torque_permille", at_least=0, at_most=U16),
        current_limit_ma=e.number("current_limit_mA", above=0, plausible=PLAUSIBLE_MILLIAMPS),
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
        axis_model=_axis_model(e, cycle_period_s),
        faults=_faults(e),
        switches=_switches(e),
        homing_search_deg=e.number("homing_search_deg", above=0),
        object_values=_object_values(e),
    )
    problem = config.make_plant().friction_problem()
    if problem:
        raise e.error("friction", problem)
    for table in (f, d, e):
        table.done()
    _twin_keys(e, config)
    return config
