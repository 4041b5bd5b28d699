"""Faults on purpose: a schedule of time windows in which an emulator misbehaves.

One fault is ``KIND@START[-END][:KEY=VALUE,...]`` (seconds of emulator time; no END = until the
emulator stops), e.g. ``drop@5-8``, ``delay@0-2:ms=300``, ``emcy@1:code=0x2310``,
``weld@3:relay=P1``. The same fields come from a ``[faults]`` table
(``schedule = ["drop@5-8", {kind = "delay", start_s = 0, end_s = 2, ms = 300}]``).
Everything is checked when parsed; a bad fault is one
:class:`~hil.emulators.errors.EmulatorSetupError`
line naming it.

The bench emulator (:mod:`hil.emulators.bench.server`) plays the Modbus and plant kinds, the drive
emulator (:mod:`hil.emulators.drive.node`) the CAN kinds, the serial line between a master and an
emulator (:mod:`hil.emulators.null_modem`) the line kinds; each asks :meth:`FaultSchedule.active`
while it serves, and the schedule records every fault the first time it takes effect
(:attr:`FaultSchedule.events`, and one ``hil: fault: ...`` line through ``on_event``).
"""

from __future__ import annotations

import math
import re
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from hil.emulators.errors import EmulatorSetupError

# kind -> (emulator, {param: (type, default or None = required, check, description)})
_Param = tuple[type, Any, Callable[[Any], bool], str]


def _positive(value: Any) -> bool:
    return bool(value > 0)


def _any(_value: Any) -> bool:
    return True


def _modbus_code(value: Any) -> bool:
    return bool(1 <= value <= 0x7F)


def _u16(value: Any) -> bool:
    return bool(0 < value <= 0xFFFF)


def _unit(value: Any) -> bool:
    return bool(0 <= value <= 247)


def _fraction(value: Any) -> bool:
    return bool(0 < value <= 1)


_UNIT: _Param = (int, 0, _unit, "Modbus unit id it applies to (0 = every unit)")

KINDS: dict[str, tuple[str, dict[str, _Param]]] = {
    # Modbus (bench emulator, TCP and RTU)
    "delay": ("bench", {"ms": (float, None, _positive, "answer this many ms late"),
                        "unit": _UNIT}),
    "drop": ("bench", {"every": (int, 1, _positive, "drop every Nth answer (1 = all)"),
                       "unit": _UNIT}),
    "exception": ("bench", {"code": (int, 4, _modbus_code, "Modbus exception code"),
                            "unit": _UNIT}),
    "close": ("bench", {"unit": _UNIT}),
    "corrupt_crc": ("bench", {"unit": _UNIT}),
    # plant (bench emulator)
    "freeze": ("bench", {"device": (str, None, lambda v: v in ("meter", "levels"),
                                    "meter | levels")}),
    "weld": ("bench", {"relay": (str, None, bool, "relay whose contact stays as it is")}),
    "load_step": ("bench", {"va": (float, None, _any, "extra apparent power, VA")}),
    # CAN (drive emulator)
    "drop_tpdo": ("drive", {"every": (int, 1, _positive, "drop every Nth TPDO (1 = all)")}),
    "delay_tpdo": ("drive", {"ms": (float, None, _positive, "send TPDOs this many ms late")}),
    "no_heartbeat": ("drive", {}),
    "silent": ("drive", {}),
    "emcy": ("drive", {"code": (int, 0x2310, _u16, "EMCY error code, e.g. 0x2310, 0x4310")}),
    "ignore_controlword": ("drive", {}),
    # serial line (a null modem between a master and an emulator), both directions
    "noise": ("line", {"rate": (float, None, _fraction,
                                "fraction of the bytes flipped, one bit each (0.0002 = 1 in "
                                "5000)"),
                       "seed": (int, 0, _any, "seed of the bytes and bits flipped")}),
}
_SPEC = re.compile(r"^(?P<kind>[a-z_]+)@(?P<start>[0-9.eE+]+)(?:-(?P<end>[0-9.eE+]+))?"
                   r"(?::(?P<params>.*))?$")
FORM = "KIND@START[-END][:KEY=VALUE,...]"


@dataclass(frozen=True)
class Fault:
    """One scripted fault: ``kind`` during ``[start_s, end_s)`` of emulator time."""

    kind: str
    start_s: float
    end_s: float = math.inf
    params: Mapping[str, Any] = field(default_factory=dict)

    @property
    def emulator(self) -> str:
        return KINDS[self.kind][0]

    def __str__(self) -> str:
        end = "" if math.isinf(self.end_s) else f"-{self.end_s:g}"
        extra = ",".join(f"{k}=0x{v:04X}" if (self.kind, k) in HEX_PARAMS else f"{k}={v}"
                         for k, v in self.params.items())
        return f"{self.kind}@{self.start_s:g}{end}" + (f":{extra}" if extra else "")

    def covers(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.end_s


#: parameters written in hex, as the standards write them (CiA 301 EMCY codes)
HEX_PARAMS = {("emcy", "code")}


def _number(text: str, kind: type, what: str) -> Any:
    try:
        return int(text, 0) if kind is int else float(text)
    except ValueError:
        raise EmulatorSetupError(
            f"{what}: {text!r} is not {'an integer' if kind is int else 'a number'}"
     ) from None


def make_fault(kind: str, start_s: Any, end_s: Any, params: Mapping[str, Any], what: str
               ) -> Fault:
    """A checked :class:`Fault`; ``what`` names it in errors (a flag, a file and key)."""
    if kind not in KINDS:
        raise EmulatorSetupError(f"{what}: unknown fault kind {kind!r} (kinds: {', '.join(KINDS)})")
    for name, value in (("start", start_s), ("end", end_s)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value) \
                or value < 0:
            raise EmulatorSetupError(f"{what}: {name} time must be a number >= 0 s, got {value!r}")
    if not end_s > start_s:
        raise EmulatorSetupError(f"{what}: the window ends ({end_s:g} s) before it starts "
                          f"({start_s:g} s)")
    known = KINDS[kind][1]
    out: dict[str, Any] = {}
    for name, value in params.items():
        if name not in known:
            raise EmulatorSetupError(f"{what}: {kind} has no parameter {name!r} "
                              f"(parameters: {', '.join(known) or 'none'})")
        expected, _default, check, description = known[name]
        if isinstance(value, str) and expected is not str:
            value = _number(value, expected, f"{what}: {name}")
        if expected is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, expected) or isinstance(value, bool) or not check(value):
            raise EmulatorSetupError(f"{what}: {name} = {value!r} is not valid ({description})")
        out[name] = value
    for name, (_type, default, _check, description) in known.items():
        if name not in out:
            if default is None:
                raise EmulatorSetupError(f"{what}: {kind} needs {name}= ({description})")
            out[name] = default
    ordered = {name: out[name] for name in known}  # one spelling per fault, whatever the order
    return Fault(kind, float(start_s), float(end_s), ordered)


def parse_fault(text: str, what: str = "--fault") -> Fault:
    """``KIND@START[-END][:KEY=VALUE,...]`` -> :class:`Fault`."""
    match = _SPEC.match(text.strip()) if isinstance(text, str) else None
    if match is None:
        raise EmulatorSetupError(f"{what} {text!r}: expected {FORM}, e.g. drop@5-8 or "
                          "delay@0:ms=300")
    what = f"{what} {text!r}"
    start = _number(match["start"], float, what)
    end = _number(match["end"], float, what) if match["end"] else math.inf
    params: dict[str, Any] = {}
    for item in filter(None, (match["params"] or "").split(",")):
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise EmulatorSetupError(f"{what}: parameter {item!r} is not KEY=VALUE")
        params[key.strip()] = value.strip()
    return make_fault(match["kind"], start, end, params, what)


def parse_faults_table(table: Any, source: str) -> list[Fault]:
    """A ``[faults]`` table (``schedule = [...]`` of strings or inline tables)."""
    if not isinstance(table, Mapping):
        raise EmulatorSetupError(f"{source}: 'faults' must be a table")
    unknown = set(table) - {"schedule"}
    if unknown:
        raise EmulatorSetupError(f"{source}: unknown key faults.{sorted(unknown)[0]} "
                          "(known: schedule)")
    schedule = table.get("schedule", [])
    if not isinstance(schedule, list):
        raise EmulatorSetupError(f"{source}: faults.schedule must be a list")
    faults = []
    for i, item in enumerate(schedule):
        what = f"{source}: faults.schedule[{i}]"
        if isinstance(item, str):
            faults.append(parse_fault(item, what))
        elif isinstance(item, Mapping):
            params = {k: v for k, v in item.items() if k not in ("kind", "start_s", "end_s")}
            if "kind" not in item or "start_s" not in item:
                raise EmulatorSetupError(f"{what}: needs kind and start_s")
            faults.append(make_fault(str(item["kind"]), item["start_s"],
                                     item.get("end_s", math.inf), params, what))
        else:
            raise EmulatorSetupError(f"{what}: expected {FORM} or an inline table")
    return faults


def for_emulator(faults: Iterable[Fault], emulator: str, what: str = "fault") -> list[Fault]:
    """``faults``, refusing one the ``emulator`` (bench | drive | line) cannot play."""
    out = list(faults)
    for fault in out:
        if fault.emulator != emulator:
            raise EmulatorSetupError(
                f"{what} {str(fault)!r}: a {fault.emulator} emulator fault, not "
         f"one the {emulator} emulator plays")
    return out


def print_event(message: str) -> None:
    """Default event sink of a standalone emulator: one line on stderr."""
    print(f"hil: fault: {message}", file=sys.stderr, flush=True)


class FaultSchedule:
    """The faults of one emulator against its clock ``now()`` (seconds).

    :meth:`active` gives the faults of a kind in effect now and records each the first time
    (``events``: dicts with ``t_s``, ``fault``, ``kind`` and ``unix_s``, the wall clock, to
    line it up with a session's time stamps); :meth:`hit` counts what
    one did (answers dropped, TPDOs delayed...). Thread-safe.
    """

    def __init__(self, faults: Iterable[Fault], now: Callable[[], float],
                 on_event: Callable[[str], None] | None = None) -> None:
        self.faults = list(faults)
        self.now = now
        self.on_event = on_event
        self.events: list[dict[str, Any]] = []
        self.hits: dict[str, int] = {}
        self._started: set[int] = set()
        self._lock = threading.Lock()
        self._kinds = {f.kind for f in self.faults}

    def __bool__(self) -> bool:
        return bool(self.faults)

    def active(self, kind: str, t_s: float | None = None) -> list[Fault]:
        if kind not in self._kinds:
            return []
        t = self.now() if t_s is None else t_s
        found = [f for f in self.faults if f.kind == kind and f.covers(t)]
        for fault in found:
            if id(fault) not in self._started:
                self._record(fault, t)
        return found

    def _record(self, fault: Fault, t_s: float) -> None:
        with self._lock:
            if id(fault) in self._started:
                return
            self._started.add(id(fault))
            unix_s = time.time()
            self.events.append({"t_s": t_s, "fault": str(fault), "kind": fault.kind,
                                "unix_s": unix_s})
        if self.on_event is not None:
            self.on_event(f"{fault} injected at t={t_s:.3f} s (unix time {unix_s:.3f})")

    def hit(self, fault: Fault) -> int:
        """Count one action of ``fault``; return the count (1 for the first)."""
        with self._lock:
            key = str(fault)
            self.hits[key] = self.hits.get(key, 0) + 1
            return self.hits[key]
