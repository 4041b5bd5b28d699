"""The Python API of hil: the same things as the command line, from a script or a test.

::

    from hil import api

    kpis = api.run_bench(MyBenchController, {"on_below": 75}, cycles=1)   # lockstep emulator
    kpis = api.run_servo("pid", duration_s=1.0, limits=["rms_error_deg<=0.5"])
    kpis = api.run_servo("setpoint", drive_overrides={"master": {"mode": "csp"}})  # CSP
    kpis = api.home_drive(method=37, offset_deg=0.0)   # HM, then a PP move (as the CLI)
    kpis = api.move_drive(90.0, velocity_deg_s=45.0)
    with api.start_drive_emulator() as emulator:        # its own process, a free port
        kpis = api.run_servo(MyServoController, drive=emulator.url, duration_s=0.5)
    with api.open_bench("modbus-tcp://192.168.0.50:502") as bench:
        bench.read_power(); bench.set_relays({"P1": True})

``run_bench`` and ``run_servo`` return the KPI dictionary of ``hil bench|servo run --json``
(``mcap`` is the session file); with ``limits`` it also has ``passed`` and ``limits``;
``home_drive`` and ``move_drive`` that of ``hil drive home|move --json``. A
controller is a class (or factory) or a spec string (``"eec"``, ``"my_ctl.py:Threshold"``,
``"package.module:Class"``). Errors are :class:`~hil.errors.HilError` with a one-line
message; a controller that raises, answers wrongly or overruns its budget ends the run with a
:class:`~hil.errors.ControllerError`, the hardware in its safe state.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import fields
from typing import TYPE_CHECKING, Any

from hil.contracts import EventSink, no_event
from hil.core.verdict import Limit, parse_limit
from hil.drivers.bench.safe_bench import SafeBench
from hil.drivers.canopen import CanDriveMaster
from hil.emulator_process import EmulatorProcess, start_bench_emulator, start_drive_emulator
from hil.errors import UsageError
from hil.servo.defaults import DEFAULT_REFERENCE

if TYPE_CHECKING:
    from hil.core.run import TunerStarted

__all__ = ["EmulatorProcess", "home_drive", "move_drive", "open_bench", "open_drive",
           "run_bench", "run_servo", "start_bench_emulator", "start_drive_emulator"]

Controller = str | Callable[..., Any]


def _limits(limits: Iterable[str | Limit]) -> tuple[Limit, ...]:
    return tuple(lim if isinstance(lim, Limit) else parse_limit(lim) for lim in limits)


def _check_options(options: Mapping[str, Any], known: Iterable[str], what: str) -> None:
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise UsageError(f"{what}: unknown option {unknown[0]!r} (known: "
                         f"{', '.join(sorted(known))})")


def run_bench(controller: Controller, params: Mapping[str, Any] | None = None, *,
              bench: str | None = None, cycles: int = 1, limits: Iterable[str | Limit] = (),
              tuner_started: TunerStarted | None = None, **options: Any) -> dict[str, Any]:
    """One closed-loop bench run (``hil bench run``); ``options`` are the other fields of
    :class:`hil.bench.run.BenchRunOptions` (``out``, ``realtime``, ``config_path``,
    ``dwell_s``, ``seed``, ``disturbance``, ``controller_budget_s``...);
    ``tuner_started(tuner)``: given the run's :class:`~hil.core.tuning.Tuner` before the
    first tick, to change parameters while it runs."""
    from hil.bench.run import BenchRunOptions
    from hil.bench.run import run_bench as run

    _check_options(options, {f.name for f in fields(BenchRunOptions)}, "run_bench")
    return run(BenchRunOptions(controller=controller, params=dict(params or {}), bench=bench,
                               cycles=cycles, limits=_limits(limits), **options),
               tuner_started=tuner_started).kpis


def run_servo(controller: Controller, params: Mapping[str, Any] | None = None, *,
              drive: str | None = None, reference: str = DEFAULT_REFERENCE,
              duration_s: float = 1.0, limits: Iterable[str | Limit] = (),
              tuner_started: TunerStarted | None = None, **options: Any) -> dict[str, Any]:
    """One closed-loop servo run (``hil servo run``), lockstep unless ``realtime=True``, on
    the drive at ``drive`` (None: the config's ``[bus]``, by default the emulated drive);
    ``options`` are the other fields of :class:`hil.servo.run.ServoRunOptions` (``out``,
    ``umax``, ``settle_s``, ``drive_config``, ``controller_budget_s``, ``axes="x=1,y=2"``
    for several axes...); ``tuner_started(tuner)``: given the run's
    :class:`~hil.core.tuning.Tuner` before the first tick, to change parameters while it
    runs (:mod:`hil.core.tuning`)."""
    from hil.servo.run import ServoRunOptions, run_servo

    _check_options(options, {f.name for f in fields(ServoRunOptions)}, "run_servo")
    return run_servo(ServoRunOptions(controller=controller, params=dict(params or {}), drive=drive,
                               reference=reference, duration_s=duration_s,
                               limits=_limits(limits), **options),
                     tuner_started=tuner_started).kpis


def move_drive(target_deg: float, drive: str | None = None, *, relative: bool = False,
               **settings: Any) -> dict[str, Any]:
    """A profile position move (``hil drive move``) of the drive at ``drive`` (None: the
    config's ``[bus]``) to ``target_deg`` (by it with ``relative``), lockstep unless
    ``realtime=True``. ``settings``: the motion's own (``velocity_deg_s``,
    ``acceleration_deg_s2``, ``deceleration_deg_s2``, ``timeout_s``) and the other fields of
    :class:`hil.servo.motion.MotionOptions` (``out``, ``node``, ``drive_config``...)."""
    return _motion("move", target_deg, drive, relative, settings)


def home_drive(drive: str | None = None, **settings: Any) -> dict[str, Any]:
    """A homing (``hil drive home``) of the drive at ``drive``, lockstep unless
    ``realtime=True``. ``settings``: the homing's own (``method``, ``offset_deg``,
    ``switch_speed_deg_s``, ``zero_speed_deg_s``, ``homing_acceleration_deg_s2``,
    ``timeout_s``) and the other fields of :class:`hil.servo.motion.MotionOptions`."""
    return _motion("home", None, drive, False, settings)


def _motion(motion: str, target_deg: float | None, drive: str | None, relative: bool,
            settings: dict[str, Any]) -> dict[str, Any]:
    from hil.servo.motion import MOTION_KEYS, MotionOptions, run_motion_options

    table = "profile" if motion == "move" else "homing"
    names = {**MOTION_KEYS, "timeout_s": f"{table}.timeout_s"}
    keys = {names[name]: (settings.pop(name), f"{motion}_drive({name}=)")
            for name in list(settings) if name in names and settings[name] is not None}
    _check_options(settings, {f.name for f in fields(MotionOptions)} - {"motion", "keys"},
                   f"{motion}_drive")
    return run_motion_options(MotionOptions(motion, target_deg, relative, keys, drive=drive,
                                            **settings)).kpis


class _MonotonicTime:
    """The time a device paces its dwell and reconnections by, outside a session."""

    @staticmethod
    def time_ns() -> int:
        return time.monotonic_ns()


@contextlib.contextmanager
def open_bench(url: str | None = None, config_path: str | None = None, *,
               on_event: EventSink = no_event,
               timeout_s: float | None = None) -> Iterator[SafeBench]:
    """The relay bench at ``url`` (None: the config's ``[bus] url``) behind its safety layer,
    relays at their safe levels; closed (relays safe, link released) on exit. ``emulated``
    serves the emulator in this process on a free loopback port, following the wall clock, for
    the time of the block. ``timeout_s``: how long the link waits for each answer, over the
    config's ``[bus] timeout_s``."""
    from dataclasses import replace

    from hil.bench.config import load_bench_config
    from hil.bench.emulated import make_emulator
    from hil.bench.openers import is_emulated, safe_bench

    config = load_bench_config(config_path)
    if timeout_s is not None:
        config = replace(config, bus=replace(config.bus, timeout_s=timeout_s))
    url = url or config.bus.url
    emulator = None
    if is_emulated(url):
        emulator = make_emulator(config)
        url = emulator.serve_tcp()
        emulator.run_realtime()
    try:
        bench = safe_bench(url, config, _MonotonicTime(), on_event)
        try:
            yield bench
        finally:
            bench.close()
    finally:
        if emulator is not None:
            emulator.stop()


@contextlib.contextmanager
def open_drive(url: str | None = None, config_path: str | None = None, *,
               on_event: EventSink = no_event) -> Iterator[CanDriveMaster]:
    """The CiA 402 drive at ``url`` (None: the config's ``[bus]``), opened and configured (not
    enabled: call ``enable()``); quick-stopped, disabled and released on exit. ``emulated``
    is the drive emulator in lockstep on a private bus: it moves one period per exchange."""
    from hil.servo.config import load_drive_config
    from hil.servo.rig import open_drive as open_master

    master = open_master(url, load_drive_config(config_path), on_event=on_event)
    try:
        master.open()
        master.configure()
        yield master
    finally:
        master.close()
