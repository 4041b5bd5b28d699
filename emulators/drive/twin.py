"""The emulated drive's dictionary: hil's own (:mod:`hil.emulators.drive.od`), or a twin of a
real drive built from its EDS or DCF (``[emulator] eds``, ``hil emulate drive --eds``), read
with canopen's ``import_od``.

A twin takes from the file every object with its power-on value (a DCF's ParameterValue, else
the DefaultValue), the PDOs as mapped at power-on, the units of its axis (0x608F encoder
increments per motor revolution, 0x6091 gear ratio: one turn of the axis is that many counts
of 0x6064; 0x6075 rated current; 0x6072 max torque and 0x6073 max current limit the
current), the modes it supports (0x6502) and its identity (0x1018). Each of its objects is one of:

* emulated - an object whose behaviour hil's node has (hil's own dictionary, the PDO objects,
  0x6091, 0x6073 max current, 0x607E at 0): the file's type must be hil's, its access and
  value are the file's; a write the node has no behaviour for (the file makes writable what
  hil's drive only reads, 0x608F, 0x1014...) is refused with 0x08000020;
* plain - a constant (access ``const``) or a description without behaviour (0x1000, 0x1008,
  0x1009, 0x100A, 0x1018, 0x6402..0x6404, 0x6503..0x6505): read back as the file gives it,
  stored when an integer is written; without a value in the file it reads 0x08000024 (the
  device type 0x1000, which every CANopen device answers, must have one: from ``set``);
* not emulated - every other object (manufacturer objects, 0x1003, 0x6073...): a read is
  refused with 0x08000024 (no data available: the twin has no value that means what the
  drive's does), a write with 0x08000020 (data cannot be stored to the application), never
  a value made up;
* hidden - hil's objects the file lacks: the node keeps them but SDO says they do not exist
  (0x06020000), as the drive would.

hil's manufacturer objects (0x2001..0x2004, :mod:`hil.emulators.drive.od`) stay where the file
has no object of their index (or has hil's own, an EDS hil wrote); an object of the file at
one of them is not emulated and the hook is gone. The time base 0x2005, by which a lockstep
master gives the drive its SYNCs' time, stays in every twin: a file's own object there (maxon's
RS232 frame timeout, Nanotec's CANopen baud rate...) is not emulated either way, and without
it lockstep would leave the twin on its own clock, its SYNC watchdog on the wall clock. The
modes are those 0x6502 lists that hil emulates (:data:`hil.emulators.drive.modes.EMULATED_MODES`)
and whose objects the file has (``MODE_NEEDS``); another mode it lists is refused with
0x08000020 when 0x6060 is set to it, one it does not list with 0x06090030, as the drive
would.

Vendor files as they come: a value left empty for commissioning comes from ``set``
(``[emulator] set``, ``--set``; a DCF's ParameterValue is the file's value), which also gives a
unit the file lacks onto hil's hidden object; a signed type is taken where CiA 402's values
are never negative (``UNSIGNED_IN_USE``); a power-on PDO map the twin cannot serve is emptied
for the master to write its own (named in :meth:`DriveDictionary.summary`), a PDO invalid at
power-on is not looked at further. A file the twin cannot run is an
:class:`~hil.emulators.errors.EmulatorSetupError` naming the file, the deciding reason (no mode
it lists that hil emulates) on its first line, every other problem one a line.
"""

from __future__ import annotations

import configparser
import logging
import struct
from collections.abc import Iterable
from dataclasses import dataclass, replace
from fractions import Fraction
from typing import Any

from canopen import import_od
from canopen.objectdictionary import ObjectDictionary, ODVariable
from canopen.objectdictionary.datatypes import (
    INTEGER8,
    INTEGER16,
    INTEGER32,
    UNSIGNED8,
    UNSIGNED16,
    UNSIGNED32,
)

from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.modes import EMULATED_MODES
from hil.emulators.drive.objects import Key, ObjectStore
from hil.emulators.drive.od import build_object_dictionary, emulator_signature, iter_variables
from hil.emulators.drive.pdo import EXTENDED_ID, MAPPING_OFFSET, MAX_PDO_BITS
from hil.emulators.drive.timebase import TIME_BASE
from hil.emulators.errors import EmulatorSetupError
from hil.protocols.cia301 import (
    ABORT_CANNOT_STORE,
    ABORT_NO_DATA,
    ABORT_VALUE,
    DEVICE_TYPE,
    IDENTITY,
    RPDO_COMM_BASE,
    TPDO_COMM_BASE,
    SdoAbortError,
    abort_text,
)
from hil.protocols.cia306 import description_encoding
from hil.protocols.cia402 import (
    CONTROLWORD,
    CYCLIC_SYNCHRONOUS_POSITION,
    CYCLIC_SYNCHRONOUS_TORQUE,
    CYCLIC_SYNCHRONOUS_VELOCITY,
    ENCODER_RESOLUTION,
    GEAR_RATIO,
    HOMING_METHOD,
    HOMING_MODE,
    HOMING_SPEEDS,
    MAX_CURRENT,
    MAX_TORQUE,
    MODE_SHORT_NAMES,
    MODES_DISPLAY,
    MODES_OF_OPERATION,
    NO_MODE,
    PDO_NOT_VALID,
    POLARITY,
    POSITION_ACTUAL,
    PROFILE_ACCELERATION,
    PROFILE_POSITION_MODE,
    PROFILE_VELOCITY,
    PROFILE_VELOCITY_MODE,
    RATED_CURRENT,
    STATUSWORD,
    SUPPORTED_MODES,
    TARGET_POSITION,
    TARGET_TORQUE,
    TARGET_VELOCITY,
)

#: hil's manufacturer objects (test hooks and time base, :mod:`hil.emulators.drive.od`)
HOOKS = (0x2001, 0x2002, 0x2003, 0x2004, TIME_BASE)
#: objects that only describe the drive: read back as the file gives them
DESCRIPTIONS = (DEVICE_TYPE, 0x1008, 0x1009, 0x100A, IDENTITY, 0x6402, 0x6403, 0x6404,
                SUPPORTED_MODES, 0x6503, 0x6504, 0x6505)
#: an EtherCAT drive's SyncManager objects (communication types, PDO assignment), which hil's
#: EtherCAT slave serves (:mod:`hil.emulators.ethercat.assignment`): the twin keeps the file's
#: power-on values for it
SYNC_MANAGER_OBJECTS = (0x1C00, 0x1C12, 0x1C13)
#: hil's node behaves by these, whatever they hold: a file must give the value it behaves by
FIXED = ((0x1014, 0, "COB-ID EMCY"), (0x1200, 1, "SDO request COB-ID"),
         (0x1200, 2, "SDO response COB-ID"))
#: the axis' units and current limits: the file must give their values (never hil's)
VALUED = (ENCODER_RESOLUTION, GEAR_RATIO, RATED_CURRENT, MAX_TORQUE, MAX_CURRENT)
#: what the twin needs to run any mode at all
NEEDED = ((CONTROLWORD, 0, "controlword"), (STATUSWORD, 0, "statusword"),
          (MODES_OF_OPERATION, 0, "modes of operation"),
          (MODES_DISPLAY, 0, "modes of operation display"),
          (POSITION_ACTUAL, 0, "position actual value"))
#: what every CANopen device answers (CiA 301): a file may leave it empty all the same (Pilz's
#: and SCHUNK's DCFs give no device type), and a master reads it first
MANDATORY = ((DEVICE_TYPE, 0, "device type"),)
#: the axis' unit: from the file, or (a file without it) from ``set`` onto hil's hidden one
UNIT = ((ENCODER_RESOLUTION, 1, "encoder increments"),
        (ENCODER_RESOLUTION, 2, "motor revolutions"))
#: what each mode needs besides, when 0x6502 lists it (a mode lacking one is not emulated)
MODE_NEEDS = {
    PROFILE_POSITION_MODE: ((TARGET_POSITION, 0, "target position"),
                            (PROFILE_VELOCITY, 0, "profile velocity"),
                            (PROFILE_ACCELERATION, 0, "profile acceleration")),
    PROFILE_VELOCITY_MODE: ((TARGET_VELOCITY, 0, "target velocity"),
                            (PROFILE_ACCELERATION, 0, "profile acceleration")),
    HOMING_MODE: ((HOMING_METHOD, 0, "homing method"),
                  (HOMING_SPEEDS, 1, "speed during search for switch"),
                  (HOMING_SPEEDS, 2, "speed during search for zero")),
    CYCLIC_SYNCHRONOUS_POSITION: ((TARGET_POSITION, 0, "target position"),),
    CYCLIC_SYNCHRONOUS_VELOCITY: ((TARGET_VELOCITY, 0, "target velocity"),),
    CYCLIC_SYNCHRONOUS_TORQUE: ((TARGET_TORQUE, 0, "target torque"),
                                (RATED_CURRENT, 0, "motor rated current")),
}
#: objects CiA 402 gives a range of non-negative values: a file may declare them signed
#: (Nanotec's 0x608F is INTEGER32), the twin then takes values 0..the signed type's maximum
UNSIGNED_IN_USE = (ENCODER_RESOLUTION, GEAR_RATIO, RATED_CURRENT, MAX_TORQUE, MAX_CURRENT,
                   0x6065, 0x6067, 0x6068, 0x606D, 0x606E, 0x606F, PROFILE_VELOCITY,
                   PROFILE_ACCELERATION, 0x6084, HOMING_SPEEDS, 0x609A)
SIGNED_OF = {UNSIGNED8: INTEGER8, UNSIGNED16: INTEGER16, UNSIGNED32: INTEGER32}
TYPE_NAMES = {1: "BOOLEAN", 2: "INTEGER8", 3: "INTEGER16", 4: "INTEGER32", 5: "UNSIGNED8",
              6: "UNSIGNED16", 7: "UNSIGNED32", 8: "REAL32", 9: "VISIBLE_STRING"}
PDO_SPAN = MAPPING_OFFSET  # 0x1400..0x15FF, 0x1800..0x19FF; their mappings 0x200 above


@dataclass(frozen=True)
class DriveDictionary:
    """The node's dictionary and what it cannot emulate (:mod:`hil.emulators.drive.objects`);
    ``modes``: what 0x6060 takes; ``path``: the EDS of a twin (None: hil's own)."""

    od: ObjectDictionary
    hidden: tuple[ODVariable, ...] = ()
    no_read: frozenset[Key] = frozenset()
    no_write: frozenset[Key] = frozenset()
    modes: frozenset[int] = frozenset((NO_MODE, *EMULATED_MODES))
    listed_modes: frozenset[int] = frozenset(EMULATED_MODES)  # 0x6502's
    counts_per_turn: int | None = None  # 0x6064 counts per turn of the axis (None: config's)
    path: str | None = None
    replaced_hooks: tuple[int, ...] = ()
    time_base_over: str | None = None  # the file's object at 0x2005, under hil's time base
    unserved_maps: tuple[str, ...] = ()  # valid PDOs whose power-on map was emptied
    motor_turns_per_turn: Fraction = Fraction(1)  # 0x6091: the index pulse's period

    def store(self) -> ObjectStore:
        return ObjectStore(self.od, hidden=self.hidden, no_read=self.no_read,
                           no_write=self.no_write)

    def configure(self, config: DriveEmulatorConfig) -> DriveEmulatorConfig:
        """``config`` with the twin's axis units."""
        if self.counts_per_turn is None:
            return config
        index_period_deg = float(360 / self.motor_turns_per_turn)
        return replace(config, increments_per_rev=self.counts_per_turn,
                       switches=replace(config.switches, index_period_deg=index_period_deg))

    def check_mode(self, mode: int) -> None:
        """Whether 0x6060 takes ``mode``: a mode 0x6502 lists that hil does not emulate is
        refused with 0x08000020, one it does not list with 0x06090030."""
        if mode in self.modes:
            return
        raise SdoAbortError(ABORT_CANNOT_STORE if mode in self.listed_modes else ABORT_VALUE)

    def unemulated(self) -> list[str]:
        """What the twin refuses: ``0x2100`` (not emulated), ``0x1800:6``, ``0x1014 (writes)``,
        ``modes PP, HM``."""
        items = []
        for index in sorted({key[0] for key in self.no_read | self.no_write}):
            subs = [var.subindex for var in iter_variables(self.od) if var.index == index]
            refused = [s for s in subs if (index, s) in self.no_read]
            written = [s for s in subs if (index, s) in self.no_write and s not in refused]
            if refused:
                items.append(f"0x{index:04X}" if len(refused) == len(subs) else
                             ", ".join(f"0x{index:04X}:{s}" for s in refused))
            if written:
                items.append(f"0x{index:04X}" + ("" if len(subs) == 1 else
                             ":" + "/".join(map(str, written))) + " (writes)")
        modes = sorted(self.listed_modes - self.modes)
        if modes:
            items.append("modes " + ", ".join(MODE_SHORT_NAMES.get(m, str(m)) for m in modes))
        return items

    def report(self) -> list[str]:
        """What the twin refuses, one object a line, with the abort code it answers."""
        names = {(v.index, v.subindex): v.name for v in iter_variables(self.od)}
        lines = []
        for title, keys in (
                (f"not emulated (read: {abort_text(ABORT_NO_DATA)}; write: "
                 f"{abort_text(ABORT_CANNOT_STORE)})", self.no_read),
                (f"writes not emulated ({abort_text(ABORT_CANNOT_STORE)})",
                 self.no_write - self.no_read)):
            if keys:
                lines.append(f"{title}:")
                lines += [f"  {_name(key)} {names[key]}" for key in sorted(keys)]
        modes = sorted(self.listed_modes - self.modes)
        if modes:
            lines.append(f"modes 0x6502 lists, not emulated (0x6060 write: "
                         f"{abort_text(ABORT_CANNOT_STORE)}): "
                         + ", ".join(MODE_SHORT_NAMES.get(m, str(m)) for m in modes))
        return lines or ["every object is emulated"]

    def summary(self, node_id: int) -> str:
        """One line: the twin, what it took from its file and what it refuses."""
        values = {(v.index, v.subindex): v.default for v in iter_variables(self.od)}
        identity = ", ".join(f"{name} 0x{values[(IDENTITY, s)]:X}"
                             for s, name in ((1, "vendor"), (2, "product"), (3, "revision"))
                             if isinstance(values.get((IDENTITY, s)), int)
                             and (IDENTITY, s) not in self.no_read)
        gear = f"{values.get((GEAR_RATIO, 1), 1)}:{values.get((GEAR_RATIO, 2), 1)}"
        modes = ", ".join(MODE_SHORT_NAMES[m] for m in sorted(self.modes - {NO_MODE}))
        refused = self.unemulated()
        hooks = ", ".join(f"0x{h:04X}" for h in self.replaced_hooks)
        increments = values.get((ENCODER_RESOLUTION, 1)) or next(
            var.default for var in self.hidden if (var.index, var.subindex) ==
            (ENCODER_RESOLUTION, 1))
        return (f"twin of {self.path} (node {node_id}): {identity or 'no identity'}; "
                f"{self.counts_per_turn} counts per turn (0x608F "
                f"{increments} increments, gear {gear}); modes {modes}; "
                f"not emulated: {', '.join(refused) or 'none'}"
                + (f"; hil's {hooks} replaced by its own" if hooks else "")
                + (f"; hil's time base 0x{TIME_BASE:04X} over its {self.time_base_over}"
                   if self.time_base_over else "")
                + (f"; power-on maps left for the master to write: "
                   f"{', '.join(self.unserved_maps)}" if self.unserved_maps else ""))


def drive_dictionary(config: DriveEmulatorConfig) -> DriveDictionary:
    """hil's own dictionary (with the power-on values ``set`` gives), or the twin of
    ``config.eds``."""
    if config.eds is not None:
        return eds_twin(config.eds, config)
    od = build_object_dictionary(config.node_id, config.od_defaults())
    variables = {(var.index, var.subindex): var for var in iter_variables(od)}
    for key, value in config.object_values:
        if key not in variables:
            raise EmulatorSetupError(f"set {_name(key)}: hil's drive has no such object")
        variables[key].default = value
    return DriveDictionary(od)


def _import(path: str, node_id: int) -> ObjectDictionary:
    """The file read by canopen (its warnings about objects it skips kept off stderr: an
    object the twin lacks is refused by SDO like any other it does not have)."""
    eds_log = logging.getLogger("canopen.objectdictionary.eds")
    level = eds_log.level
    eds_log.setLevel(logging.ERROR)
    try:
        od: ObjectDictionary = _read_od(path, node_id)
    except (OSError, ValueError, KeyError, configparser.Error) as exc:
        reason = getattr(exc, "strerror", None) or str(exc).splitlines()[0]
        raise EmulatorSetupError(f"{_kind(path)} {path}: cannot read it: {reason}") from None
    finally:
        eds_log.setLevel(level)
    return od


def _read_od(path: str, node_id: int) -> ObjectDictionary:
    """canopen's reading of the file's text, in its encoding (one that is not UTF-8, a
    vendor's comment in Windows-1252, read as Latin-1); an ESI file's (``.xml``) CoE objects
    as the same dictionary."""
    if path.lower().endswith(".xml"):
        from hil.emulators.ethercat.esi_dictionary import od_from_esi

        return od_from_esi(path, node_id)
    with open(path, encoding=description_encoding(path)) as text:
        od: ObjectDictionary = import_od(text, node_id)
    return od


def _kind(path: str) -> str:
    """What the file is, as its lines name it: ``ESI`` (an EtherCAT ``.xml``) or ``EDS``."""
    return "ESI" if path.lower().endswith(".xml") else "EDS"


def _value(var: ODVariable) -> object:
    """The power-on value the file gives (a DCF's ParameterValue, else the DefaultValue)."""
    return var.value if var.value is not None else var.default


def _name(key: Key) -> str:
    return f"0x{key[0]:04X}:{key[1]}"


def _gear_template() -> dict[int, ODVariable]:
    """0x6091 as the twin emulates it: read, the axis built with it."""
    out = {}
    for sub, data_type in ((0, UNSIGNED8), (1, UNSIGNED32), (2, UNSIGNED32)):
        var = ODVariable("Gear ratio", GEAR_RATIO, sub)
        var.data_type, var.access_type, var.default = data_type, "ro", 2 if sub == 0 else 1
        out[sub] = var
    return out


def _polarity_template() -> ODVariable:
    var = ODVariable("Polarity", POLARITY, 0)
    var.data_type, var.access_type, var.default = UNSIGNED8, "ro", 0
    return var


def _max_current_template() -> ODVariable:
    """0x6073 as the twin emulates it: the current loops' limit, with 0x6072."""
    var = ODVariable("Max current", MAX_CURRENT, 0)
    var.data_type, var.access_type, var.default = UNSIGNED16, "rw", 0xFFFF
    var.pdo_mappable = True
    return var


class _Twin:
    """The steps of building a twin from one file. Each problem found is kept (one line
    each) and the twin refused with all of them, the deciding one first."""

    def __init__(self, path: str, config: DriveEmulatorConfig) -> None:
        self.path, self.node_id = path, config.node_id
        self.od = _import(path, config.node_id)
        self.own = build_object_dictionary(config.node_id, config.od_defaults())
        self.own_vars = {(v.index, v.subindex): v for v in iter_variables(self.own)}
        self.settings = dict(config.object_values)
        self.od_defaults = config.od_defaults()
        self.defaulted: list[ODVariable] = []  # given hil's default: the file has no value
        self.no_read: set[Key] = set()
        self.no_write: set[Key] = set()
        self.replaced: list[int] = []
        self.time_base_over: str | None = None
        self.gear = _gear_template()
        self.problems: list[str] = []
        self.unserved: list[str] = []  # PDOs whose power-on map the twin cannot serve
        self.motor_turns_per_turn = Fraction(1)  # 0x6091's gear

    def error(self, text: str) -> EmulatorSetupError:
        return EmulatorSetupError(f"{_kind(self.path)} {self.path}: {text}")

    def problem(self, text: str) -> None:
        self.problems.append(text)

    def refusal(self, deciding: str | None = None) -> EmulatorSetupError:
        """The twin refused: the deciding reason first, then every other problem, one a line."""
        lines = ([deciding] if deciding else []) + self.problems
        return EmulatorSetupError("\n".join(f"{_kind(self.path)} {self.path}: {line}"
                                           for line in lines))

    def take_hooks(self) -> None:
        """hil's manufacturer objects (:data:`HOOKS`) where the file leaves them room (the
        time base always), and its signature 0x1018:5 beside the vendor's identity."""
        identity = self.od.get(IDENTITY) if IDENTITY in self.od else None
        if identity is not None and not isinstance(identity, ODVariable):
            identity.add_member(emulator_signature())
        for index in HOOKS:
            own = self.own[index]
            if index not in self.od:
                self.od.add_object(own)
                continue
            theirs = self.od[index]
            if isinstance(theirs, ODVariable) and isinstance(own, ODVariable) \
                    and theirs.name == own.name and theirs.data_type == own.data_type:
                continue
            if index == TIME_BASE:  # lockstep's: kept over the file's
                self.time_base_over = f"{theirs.name!r}"
                del self.od[index]
                self.od.add_object(own)
            else:
                self.replaced.append(index)

    def take_settings(self) -> None:
        """The power-on values given by ``set`` (``--set``, ``[emulator] set``): over the
        file's (its DCF values too), or onto hil's own object the file lacks, which the twin
        keeps hidden (a unit, a limit)."""
        for key, value in self.settings.items():
            var = self.variable(key) or self.own_vars.get(key)
            if var is None:
                self.problem(f"set {_name(key)}: neither the file nor hil's drive has it")
                continue
            try:
                var.encode_raw(value)
            except (struct.error, ValueError, TypeError):
                self.problem(f"set {_name(key)} = {value}: out of the range of its type "
                             f"{TYPE_NAMES.get(var.data_type or 0, var.data_type)}")
                continue
            var.value = var.default = value

    def template(self, key: Key) -> ODVariable | None:
        """hil's variable of the same role, if the node emulates it."""
        index, sub = key
        if index in self.replaced:
            return None
        for base in (RPDO_COMM_BASE, TPDO_COMM_BASE):
            if base <= index < base + PDO_SPAN:
                return self.own_vars.get((base, sub))
            if base + PDO_SPAN <= index < base + 2 * PDO_SPAN:
                return self.own_vars.get((base + PDO_SPAN, min(sub, 1)))
        if index == GEAR_RATIO:
            return self.gear.get(sub)
        if key == (POLARITY, 0):
            return _polarity_template()
        if key == (MAX_CURRENT, 0):
            return _max_current_template()
        return self.own_vars.get(key)

    def classify(self) -> None:
        for var in list(iter_variables(self.od)):
            key = (var.index, var.subindex)
            value = _value(var)
            template = self.template(key)
            if var.index in DESCRIPTIONS + SYNC_MANAGER_OBJECTS or (
                    var.access_type == "const" and template is None
                    and var.index not in self.replaced):
                var.default = value
                if value is None:
                    self.no_read.add(key)
            elif template is not None:
                self.emulated(var, template, value)
            else:
                var.default = value
                self.no_read.add(key)
                self.no_write.add(key)

    def emulated(self, var: ODVariable, template: ODVariable, value: Any) -> None:
        key = (var.index, var.subindex)
        if value is None and var.index in VALUED and key not in (
                (ENCODER_RESOLUTION, 0), (GEAR_RATIO, 0)):
            self.problem(f"{_name(key)} ({var.name}) has no value: the twin takes the axis' "
                         f"units and current limits from the file, never its own; "
                         f"{_how_to_set(key)}")
            value = template.default
        if var.data_type != template.data_type:
            if not (var.index in UNSIGNED_IN_USE
                    and SIGNED_OF.get(template.data_type or 0) == var.data_type):
                self.problem(
                    f"{_name(key)} ({var.name}) is "
                    f"{TYPE_NAMES.get(var.data_type or 0, var.data_type)}, the twin's is "
                    f"{TYPE_NAMES.get(template.data_type or 0)}")
                return
            var.min = max(var.min or 0, 0)  # signed in the file, CiA 402's values are not
        if value is None:
            self.defaulted.append(var)
        var.default = template.default if value is None else value
        var.min = template.min if var.min is None else var.min
        var.max = template.max if var.max is None else var.max
        if var.writable and not template.writable:
            self.no_write.add(key)
        fixed = next((name for index, sub, name in FIXED if key == (index, sub)), None)
        if fixed is not None and var.default != template.default:
            self.problem(f"{_name(key)} ({fixed}) is 0x{var.default:X}; the twin's is "
                         f"0x{template.default:X}, as CiA 301 predefines it")

    def variable(self, key: Key) -> ODVariable | None:
        """The file's object ``key``, if it has one."""
        if key[0] not in self.od:
            return None
        obj = self.od[key[0]]
        if isinstance(obj, ODVariable):
            return obj if key[1] == 0 else None
        var: ODVariable | None = obj.subindices.get(key[1])
        return var

    def value(self, index: int, sub: int = 0, default: int | None = None) -> int | None:
        """The power-on value of an object the twin serves (``default``: none)."""
        var = self.variable((index, sub))
        if var is None or (index, sub) in self.no_read or not isinstance(var.default, int):
            return default
        return var.default

    def lacks(self, needs: tuple[tuple[int, int, str], ...]) -> list[str]:
        """What of ``needs`` the file lacks or leaves without a value, one line each."""
        lacking = []
        for index, sub, name in needs:
            if self.variable((index, sub)) is None:
                if (index, sub) not in self.settings:  # set: onto hil's hidden object
                    lacking.append(f"no {_name((index, sub))} ({name}); "
                                   f"{_how_to_set((index, sub))}")
            elif self.value(index, sub) is None:
                lacking.append(f"{_name((index, sub))} ({name}) has no value; "
                               f"{_how_to_set((index, sub))}")
        return lacking

    def modes(self) -> tuple[frozenset[int], frozenset[int]]:
        """(the modes 0x6060 takes, the modes 0x6502 lists): every listed mode hil emulates
        whose objects the file has. None of them: the deciding reason, raised."""
        supported = self.value(SUPPORTED_MODES)
        listed = frozenset(bit + 1 for bit in range(10) if (supported or 0) >> bit & 1)
        names = ", ".join(MODE_SHORT_NAMES[m] for m in EMULATED_MODES)
        if supported is None:
            raise self.refusal(f"no 0x6502 (supported drive modes) with a value: the twin "
                               f"emulates the modes it lists ({names})")
        candidates = [mode for mode in EMULATED_MODES if mode in listed]
        if not candidates:
            raise self.refusal(f"lists no mode hil emulates: 0x6502 = 0x{supported:08X} "
                               f"({', '.join(_mode_names(listed)) or 'none'}); hil emulates "
                               f"{names}")
        emulated = [mode for mode in candidates if not self.lacks(MODE_NEEDS[mode])]
        if not emulated:
            lines = [f"{MODE_SHORT_NAMES[mode]}: {lack}" for mode in candidates
                     for lack in self.lacks(MODE_NEEDS[mode])]
            self.problems[:0] = lines
            raise self.refusal(f"none of the modes it lists that hil emulates "
                               f"({', '.join(_mode_names(candidates))}) has its objects:")
        modes = frozenset((NO_MODE, *emulated))
        start = self.value(MODES_OF_OPERATION, 0, NO_MODE)  # the master sets the mode it runs
        display = self.od.get(MODES_DISPLAY)
        if isinstance(display, ODVariable):
            display.default = start  # the display shows the mode in effect
        return modes, listed

    def unit_value(self, index: int, sub: int) -> int | None:
        """A unit's value: the file's, or hil's hidden object given by ``set``."""
        if self.variable((index, sub)) is not None:
            return self.value(index, sub)
        value = self.settings.get((index, sub))
        return value if isinstance(value, int) else None

    def counts_per_turn(self) -> int | None:
        for index, sub, name in UNIT:
            if self.unit_value(index, sub) is None and self.variable((index, sub)) is None:
                self.problem(f"no {_name((index, sub))} ({name}): the twin needs the axis' "
                             f"unit; {_how_to_set((index, sub))} (kept hidden, as the "
                             "drive has none)")
        increments = self.unit_value(ENCODER_RESOLUTION, 1)
        motor_turns = self.unit_value(ENCODER_RESOLUTION, 2)
        if increments is None or motor_turns is None:
            return None
        gear_motor = self.value(GEAR_RATIO, 1, 1) or 0
        gear_shaft = self.value(GEAR_RATIO, 2, 1) or 0
        if not (increments and motor_turns and gear_motor and gear_shaft):
            self.problem(f"0x608F = {increments} increments / {motor_turns} revolutions, "
                         f"0x6091 gear {gear_motor}:{gear_shaft}: a zero gives no axis unit")
            return None
        counts = Fraction(increments * gear_motor, motor_turns * gear_shaft)
        if counts.denominator != 1 or not 2 <= counts < 2**31:
            self.problem(f"0x608F and 0x6091 give {float(counts):g} counts per turn of the "
                         "axis; the twin needs a whole number in 2..2^31-1; "
                         f"{_how_to_set((ENCODER_RESOLUTION, 1))}")
            return None
        polarity = self.value(POLARITY, 0, 0)
        if polarity:
            self.problem(f"0x607E polarity is 0x{polarity:02X}: the twin does not reverse "
                         "its axis (0 only)")
        self.motor_turns_per_turn = Fraction(gear_motor, gear_shaft)
        return int(counts)

    def scale_defaults(self, counts: int) -> None:
        """hil's defaults the twin stands in with (for objects hidden or left empty, ``set``
        not giving them) in the twin's unit: its windows, speeds and accelerations are the
        same fractions of a turn as hil's own."""
        own = {(v.index, v.subindex): v.default for v in iter_variables(build_object_dictionary(
            self.node_id, replace(self.od_defaults, increments_per_rev=counts)))}
        present = {(v.index, v.subindex) for v in iter_variables(self.od)}
        hidden = [var for key, var in self.own_vars.items() if key not in present]
        for var in (*self.defaulted, *hidden):
            key = (var.index, var.subindex)
            if key not in self.settings and key in own:
                var.default = own[key]

    def serve_pdos(self, store: ObjectStore) -> None:
        """The PDOs as the file maps them at power-on. A master maps them again at configure
        (a drive's maps are dynamic), so a map the twin cannot serve is emptied, not refused:
        the master's own map is checked when it writes it (SDO abort 0x06040041). A valid
        PDO must still be of a kind the twin emulates; an invalid one (COB-ID bit 31) is
        not looked at further."""
        store.reset()
        values = store.values
        for base, transmit in ((RPDO_COMM_BASE, False), (TPDO_COMM_BASE, True)):
            for comm in range(base, base + PDO_SPAN):
                if comm + PDO_SPAN not in self.od:
                    continue
                if comm in self.od:
                    self.serve_pdo(values, comm, transmit)
                else:
                    self.serve_map(values, comm + PDO_SPAN, transmit)

    def serve_map(self, values: dict[Key, object], mapping: int, transmit: bool) -> None:
        """An EtherCAT drive's PDO (a mapping object alone, from an ESI): its power-on map
        emptied where the twin cannot serve it; no CAN frame carries it, so no 64 bits' limit."""
        why = self.unservable(mapping, values.get((mapping, 0)), transmit, frame_bits=None)
        if why is not None:
            self.empty_map(mapping)
            self.unserved.append(f"{'TxPDO' if transmit else 'RxPDO'} 0x{mapping:04X} ({why})")

    def serve_pdo(self, values: dict[Key, object], comm: int, transmit: bool) -> None:
        mapping = comm + PDO_SPAN
        name = f"{'TPDO' if transmit else 'RPDO'}{comm % PDO_SPAN + 1} (0x{comm:04X})"
        cob, kind, count = (values.get(key) for key in ((comm, 1), (comm, 2), (mapping, 0)))
        if not isinstance(cob, int):
            self.problem(f"{name}: no {_name((comm, 1))} with a value")
            return
        valid = not cob & PDO_NOT_VALID
        why = self.unservable(mapping, count, transmit)
        if why is not None:
            self.empty_map(mapping)
            if valid:
                self.unserved.append(f"{name} ({why})")
        if not valid:
            return
        if not isinstance(kind, int):
            self.problem(f"{name}: no {_name((comm, 2))} with a value")
        elif 241 <= kind <= 253:
            self.problem(f"{name} is valid at power-on with transmission type {kind}, "
                         "which the twin does not emulate (0..240, 254, 255; no RTR)")
        if cob & EXTENDED_ID:
            self.problem(f"{name} has a 29-bit COB-ID 0x{cob:08X}; the twin uses 11-bit "
                         "identifiers")

    def unservable(self, mapping: int, count: object, transmit: bool,
                   frame_bits: int | None = MAX_PDO_BITS) -> str | None:
        """Why the twin cannot serve the power-on map of ``mapping`` (None: it can), in a
        frame of ``frame_bits`` (None: no limit)."""
        if not isinstance(count, int):
            return f"{_name((mapping, 0))} has no value"
        bits = 0
        for sub in range(1, count + 1):
            var = self.variable((mapping, sub))
            entry = None if var is None else var.default
            if not isinstance(entry, int):
                return f"{_name((mapping, sub))} has no value"
            key, size = (entry >> 16, (entry >> 8) & 0xFF), entry & 0xFF
            mapped = self.variable(key)
            if mapped is None:
                return f"maps {_name(key)}, which the file does not have"
            if key in (self.no_read if transmit else self.no_write):
                return (f"maps {_name(key)} ({mapped.name}), which the twin cannot "
                        f"{'produce' if transmit else 'take'}")
            if not mapped.pdo_mappable or size != len(mapped):
                return f"maps {_name(key)} as {size} bits, not as the file declares it"
            bits += size
        if frame_bits is not None and bits > frame_bits:
            return f"maps {bits} bits, more than a CAN frame's {frame_bits}"
        return None

    def empty_map(self, mapping: int) -> None:
        var = self.variable((mapping, 0))
        if var is not None:
            var.default = 0

    def build(self) -> DriveDictionary:
        self.take_hooks()
        self.take_settings()
        self.classify()
        if _kind(self.path) == "ESI":
            from hil.emulators.ethercat.esi import fixed_pdo_problems

            for line in fixed_pdo_problems(self.path):
                self.problem(line)
        modes, listed = self.modes()  # the deciding reason, when there is one
        for lack in self.lacks(NEEDED):
            self.problem(f"{lack}: the twin needs it to run any mode")
        for lack in self.lacks(MANDATORY):
            self.problem(f"{lack}: every CANopen device has it (CiA 301), and a master "
                         "reads it first")
        counts = self.counts_per_turn()
        if counts is not None:
            self.scale_defaults(counts)
        present = {(v.index, v.subindex) for v in iter_variables(self.od)}
        hidden = tuple(var for key, var in self.own_vars.items()
                       if key not in present or key[0] in self.replaced)
        twin = DriveDictionary(self.od, hidden, frozenset(self.no_read),
                               frozenset(self.no_write), modes, listed, counts, self.path,
                               tuple(self.replaced), self.time_base_over,
                               motor_turns_per_turn=self.motor_turns_per_turn)
        if not self.problems:
            self.serve_pdos(twin.store())
        if self.problems:
            raise self.refusal()
        return replace(twin, unserved_maps=tuple(self.unserved))


def _mode_names(modes: Iterable[int]) -> list[str]:
    return [MODE_SHORT_NAMES.get(mode, str(mode)) for mode in sorted(modes)]


def _how_to_set(key: Key) -> str:
    """How a user gives an object's power-on value the file leaves empty."""
    return (f"give it with --set {_name(key)}=VALUE or [emulator] set = "
            f"{{\"{_name(key)}\" = VALUE}} (or a DCF's ParameterValue)")


def eds_twin(path: str, config: DriveEmulatorConfig) -> DriveDictionary:
    """The twin of the drive the EDS or DCF at ``path`` describes, as node ``config.node_id``
    (``$NODEID`` values resolved); EmulatorSetupError when it cannot be one."""
    return _Twin(path, config).build()

