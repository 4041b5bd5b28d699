"""A servo run's settings, resolved in one place, in one order for every key:

    built-in defaults < hil/configs/drive.toml < the user's --config < flags

Flags that set a key of drive.toml are layers over the files (``--node`` is
``master.node_id``, ``--eds`` is ``master.eds``, ``--safety K=V`` is ``safety.K``, ``--umax`` is
``master.current_limit_mA``, ``--drive URL`` is ``bus.url``, which names the bus instead of
its interface, channel and options; ``--drive 'emulated?model=F.json'``: the emulated drive,
``[emulator] model`` = F.json, its path from the working folder). What the run
uses comes from :class:`ServoSettings` only, so what ``--print-config`` shows is what runs.

Limits only tighten from a flag: ``--umax`` above the configured current limit needs
``--allow-higher-current``, a ``--safety`` value looser than the configured one needs
``--allow-looser-safety``; either is then recorded as a warning (:attr:`ServoSettings.notices`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from urllib.parse import parse_qsl

from can.interfaces import VALID_INTERFACES

from hil.controllers.base import CURRENT, OUTPUT_UNITS, check_cycle_period, outputs_of
from hil.core.params import params_origin
from hil.core.registry import scheme_of
from hil.core.settings import (
    LOWER,
    SWITCH,
    UPPER,
    Layer,
    LooseningRefusedError,
    Setting,
    lay,
    loosened,
    option_settings,
    tightened_only,
)
from hil.drivers.canopen.bus import parse_can_url
from hil.errors import ConfigError, UsageError
from hil.protocols.cia402 import OPERATION_MODES
from hil.servo.config import (
    EMULATED,
    SOURCE,
    DriveConfig,
    check_bitrate,
    drive_layers,
    parse_drive_config,
)
from hil.servo.options import ServoRunOptions, flag_of

#: the keys of drive.toml a flag sets (a ``*`` stands for any name), for the reference and
#: --help; the layers themselves are built by :func:`resolve_servo`
FLAG_KEYS = {"bus.url": "--drive", "master.node_id": "--node",
             "master.current_limit_mA": "--umax", "master.eds": "--eds",
             "emulator.model": "--drive emulated?model=F", "safety.*": "--safety KEY=VALUE"}
#: the keys of ``[emulator]`` the URL ``emulated?KEY=VALUE`` sets
EMULATED_URL_KEYS = ("model",)
#: how each safety limit of ``[safety]`` tightens
SAFETY_DIRECTIONS = {"enabled": SWITCH, "following_error_deg": UPPER,
                     "following_error_ms": UPPER, "position_min_deg": LOWER,
                     "position_max_deg": UPPER, "velocity_max_deg_s": UPPER,
                     "stale_share_max": UPPER, "stale_window_ms": UPPER}
#: the origin of the waits lockstep over a bus sets (from master.lockstep_timeout_ms)
LOCKSTEP_ORIGIN = "lockstep over a bus: master.lockstep_timeout_ms"
#: the options that land on a key of drive.toml (shown there), or are not the user's (a
#: program's overrides, the config file itself: the origins name it)
NOT_SETTINGS = ("drive_overrides", "drive_config", "drive", "node", "eds", "safety")


@dataclass(frozen=True)
class ServoSettings:
    """Everything a servo run uses, resolved: the options, the drive config with the flags laid
    in, where the drive is, the controller's current bound, and the warnings a loosened limit
    gives (event kind, message)."""

    options: ServoRunOptions
    drive: DriveConfig
    drive_url: str
    drive_url_origin: str
    umax_ma: float
    notices: tuple[tuple[str, str], ...] = ()

    def settings(self) -> list[Setting]:
        """Every setting as it runs, with its origin: the run's options, then drive.toml's
        keys (``bus.url``: where the drive is)."""
        options = self.options
        every = options.prediction_period
        defaults = ServoRunOptions.from_flags({"controller": options.controller or None},
                                              need_controller=False)
        resolved = {
            "params": (dict(options.params), "default" if not options.params
                       else params_origin(options.params, options.params_file)),
            "umax": (self.umax_ma, self._umax_origin()),
            "prediction_every": (every, "default" if options.prediction_every is None
                                 else "--prediction-every"),
            "controller": (options.controller or None,
                           "--controller" if options.controller else "not given")}
        return [*option_settings(options, defaults, resolved, NOT_SETTINGS, flag_of),
                *self._drive_settings()]

    def _umax_origin(self) -> str:
        return "--umax" if self.options.umax is not None else \
            self.drive.layered.origin("master.current_limit_mA")

    def _drive_settings(self) -> list[Setting]:
        """drive.toml's keys as they run: ``bus.url`` the bus the run drives (its ``url``,
        else what ``interface``, ``channel`` and ``options`` make, which a url leaves
        unused)."""
        named = bool(self.drive.url)
        settings = []
        for s in self.drive.settings():
            if s.key == "bus.url":
                s = Setting(s.key, self.drive_url, self.drive_url_origin, s.kind, s.rule)
            elif named and s.key.split(".")[:2] in (["bus", "interface"], ["bus", "channel"],
                                                    ["bus", "options"]):
                s = Setting(s.key, s.value, s.origin + " (unused: url names the bus)", s.kind,
                            s.rule)
            settings.append(s)
        return settings


def resolve_servo(options: ServoRunOptions) -> ServoSettings:
    """The settings of a servo run (see the module); a UsageError names a flag that would
    loosen a limit without being allowed to, a ConfigError a bad key."""
    layers, text = drive_layers(options.drive_config)
    source = os.fspath(options.drive_config) if options.drive_config is not None else SOURCE
    configured = parse_drive_config(lay(layers), source, text)
    drive_url, url_keys = emulated_url(options.drive)
    flags = _flag_layers(options)
    if drive_url is not None:  # a model's path: from the working folder
        flags.append(Layer("--drive", {"bus": {"url": drive_url}, "emulator": url_keys}))
    drive = parse_drive_config(lay([*layers, *flags]), source, text)
    notices = [*_current_limit(options, configured), *_safety(options, configured, drive)]
    if options.umax is not None:
        drive = drive.laid_over({"master": {"current_limit_mA": float(options.umax)}}, "--umax")
    if options.drive_overrides:  # a program's, last of all (tests, scripts, the demo)
        drive = drive.laid_over(options.drive_overrides, "drive_overrides")
    url = drive.bus_url
    url_origin = drive.layered.origin("bus.url" if drive.url else "bus.interface")
    buses = run_buses(options, drive, url)
    for bus in buses:
        check_emulated_period(drive, bus)
        bus_bitrate(bus, drive)
    if not options.realtime and buses != {EMULATED}:
        drive = lockstep_over_a_bus(drive)
    return ServoSettings(options, drive, url, url_origin, drive.master.current_limit_ma,
                         tuple(notices))


def lockstep_over_a_bus(drive: DriveConfig) -> DriveConfig:
    """Lockstep over a bus: the master waits ``lockstep_timeout_ms`` of wall time for every
    answer (a SYNC's TPDOs, an SDO reply of a drive that has answered before: a node never
    heard from gets ``sdo_timeout_ms``); a drive silent for all of it is gone."""
    master = drive.master
    timeout_ms = round(master.lockstep_timeout_s * 1e3)
    drive = drive.laid_over({"master": {
        "rx_timeout_us": max(round(master.rx_timeout_s * 1e6), timeout_ms * 1000)}},
        LOCKSTEP_ORIGIN)
    return replace(drive, master=replace(drive.master, lockstep=True))


def run_buses(options: ServoRunOptions, drive: DriveConfig, url: str) -> set[str]:
    """The buses a run drives: ``url`` (``--drive`` or ``[bus]``), unless every axis names
    its own (``--axes NAME=NODE@URL``, ``[[axis]] bus``), and those."""
    if options.axes:
        named = [part.partition("@")[2].strip() for part in options.axes.split(",")
                 if part.strip()]
    else:
        named = [axis.bus for axis in drive.axes] or [""]
    return {bus or url for bus in named}


def emulated_url(url: str | None) -> tuple[str | None, dict[str, str]]:
    """``emulated?model=F.json`` -> ``emulated`` and the ``[emulator]`` keys of its query
    (:data:`EMULATED_URL_KEYS`); any other URL as it is, with none. A key it does not take is a
    UsageError naming the URL."""
    if url is None or not url.startswith(EMULATED + "?"):
        return url, {}
    keys = {}
    for part in url.partition("?")[2].split("&"):
        pairs = parse_qsl(part)  # one key=value, percent-decoded; nothing when malformed
        if len(pairs) != 1 or pairs[0][0] not in EMULATED_URL_KEYS:
            raise UsageError(f"--drive {url!r}: {part!r} is not a key of the emulated drive "
                             "(it takes model=F.json: its axis as a model file)")
        keys[pairs[0][0]] = pairs[0][1]
    return EMULATED, keys


def check_emulated_period(drive: DriveConfig, url: str) -> None:
    """The emulated drive steps its axis every 500 us (a model file's: its period): its cycle
    period (SYNC, 0x1006) must be a whole multiple of it (ConfigError naming the key and the
    unit)."""
    if scheme_of(url) != EMULATED:
        return
    period_us = round(drive.master.cycle_period_s * 1e6)
    step_us = round(drive.emulator.axis_period_s * 1e6)
    if period_us % max(step_us, 1):
        raise ConfigError(f"{drive.source}: key 'master.cycle_period_us' is {period_us} us: the "
                          f"emulated drive steps its axis every {step_us} us, so its cycle "
                          f"period is a multiple of {step_us} us ({step_us}, {2 * step_us}...)")


def check_controller_period(factory: object, label: str, drive: DriveConfig) -> None:
    """The controller runs at ``master.cycle_period_us`` (what its factory's
    ``cycle_periods_us`` says: :func:`hil.controllers.base.check_cycle_period`), else one
    ConfigError naming it."""
    check_cycle_period(factory, label, round(drive.master.cycle_period_s * 1e6))


#: the modes ``hil servo run`` drives: a set point every cycle (PP takes one through its
#: handshake: ``hil drive move``; HM none: ``hil drive home``)
RUN_MODES = ("cst", "csp", "csv", "pv")
#: what a controller returns for a drive whose set point is in each unit
OUTPUT_FOR_UNIT = {unit: output for output, unit in OUTPUT_UNITS.items()}


def run_output(drive: DriveConfig) -> str:
    """What the run's controller returns: what the drive's mode (``[master] mode``) takes
    every cycle; a mode ``hil servo run`` does not drive is a UsageError naming the command
    that does."""
    mode = OPERATION_MODES[drive.master.mode]
    if mode.name not in RUN_MODES:
        other = "hil drive move" if mode.set_point is not None else "hil drive home"
        raise UsageError(f"[master] mode = {mode.name!r}: hil servo run sends a set point "
                         f"every cycle ({', '.join(m.upper() for m in RUN_MODES)}); "
                         f"{mode.short} ({mode.title}) runs with {other}")
    return OUTPUT_FOR_UNIT[str(mode.unit)]


def check_controller_output(factory: object, label: str, drive: DriveConfig) -> None:
    """The controller returns what the drive's mode takes (:func:`run_output`: a current in
    CST, a position in CSP, a velocity in CSV and PV), else one UsageError naming the mode."""
    output = run_output(drive)
    outputs = outputs_of(factory)
    if output in outputs:
        return
    mode = OPERATION_MODES[drive.master.mode]
    gives = " or ".join(f"{o} [{OUTPUT_UNITS[o]}]" for o in outputs)
    hint = "pid, mpc and empc return one" if output == CURRENT else \
        f"--controller setpoint sends the reference as one, or your own with output = {output!r}"
    raise UsageError(f"controller {label!r} returns a {gives}: a drive in {mode.short} "
                     f"({mode.title}, [master] mode = {mode.name!r}) takes a {output} "
                     f"[{OUTPUT_UNITS[output]}] every cycle; {hint}")


def bus_bitrate(url: str, drive: DriveConfig) -> int:
    """The bit rate of the bus at ``url`` [bit/s]: the URL's own ``bitrate`` option (as the
    bus is opened with it), else ``[bus] bitrate``; a URL's above classic CAN's without
    ``fd=true`` is a UsageError naming the URL."""
    if scheme_of(url) not in VALID_INTERFACES:  # emulated, a plug-in's scheme
        return drive.master.bitrate
    options = parse_can_url(url, drive.master.channel).options
    bitrate = options.get("bitrate")
    if not isinstance(bitrate, int) or isinstance(bitrate, bool):
        return drive.master.bitrate
    check_bitrate(bitrate, options.get("fd") is True, f"{url}: bitrate")
    return bitrate


def _flag_layers(options: ServoRunOptions) -> list[Layer]:
    """The flags that set keys of drive.toml (``--umax`` comes after the tightening check)."""
    layers = []
    if options.node is not None:
        layers.append(Layer("--node", {"master": {"node_id": options.node}}))
    if options.eds is not None:
        layers.append(Layer("--eds", {"master": {"eds": options.eds}}))
    if options.safety:
        layers.append(Layer("--safety", {"safety": dict(options.safety)}))
    return layers


def _current_limit(options: ServoRunOptions, configured: DriveConfig
                   ) -> list[tuple[str, str]]:
    """``--umax`` may lower the configured current limit; raising it needs
    ``--allow-higher-current`` (then a warning)."""
    limit = configured.master.current_limit_ma
    if options.umax is None or options.umax <= limit:
        return []
    origin = configured.layered.origin("master.current_limit_mA")
    if not options.allow_higher_current:
        raise LooseningRefusedError(
            f"--umax {options.umax:g} mA is above the configured current limit "
            f"(master.current_limit_mA = {limit:g} mA, {origin}): a flag may lower it, not "
            "raise it", "; --allow-higher-current raises it (recorded)")
    return [("current.limit_raised", f"--umax {options.umax:g} mA raises the configured "
             f"current limit of {limit:g} mA ({origin}): --allow-higher-current")]


def _safety(options: ServoRunOptions, configured: DriveConfig, drive: DriveConfig
            ) -> list[tuple[str, str]]:
    """``--safety`` may tighten ``[safety]``; loosening needs ``--allow-looser-safety``."""
    if not options.safety:
        return []
    before, after = configured.layered.data["safety"], drive.layered.data["safety"]
    looser = loosened(before, {k: after[k] for k in options.safety if k in after},
                      SAFETY_DIRECTIONS)
    return tightened_only(looser, "--safety", options.allow_looser_safety)
