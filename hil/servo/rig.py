"""How the servo application reaches its drive: the drive URL schemes, and the emulated drive
wired in lockstep (the driver knows nothing of the emulator).

* ``emulated`` - :class:`EmulatedDrive`, the drive emulator on a private in-process channel
  that runs the node whenever the master transmits; the emulator is also the master's clock
  (its SYNC count), so a run is deterministic and as fast as the CPU allows;
* ``socketcand://HOST:PORT[/CHANNEL]`` - a socketcand gateway (or ``hil emulate drive``);
* ``INTERFACE://CHANNEL[?key=value&...]`` - any python-can interface (``socketcan://can0``,
  ``slcan:///dev/ttyACM0?bitrate=1000000``, ``gs_usb://0``, ``pcan://PCAN_USBBUS1``,
  ``udp_multicast://239.0.0.1?port=43113``, ``virtual://bench``...);
* no URL: the ``[bus]`` table of drive.toml;
* installed packages add schemes through the ``hil.drive_devices`` entry points.

A drive factory opens the drives of the run's axes on one bus: it is called as
``factory(url, drive_config, axes, on_event=sink, trace=trace)`` (``axes``: the
:class:`~hil.servo.config.AxisSpec` of each drive on that bus, one or several) and returns a
:class:`~hil.servo.drives.BusDrives` (one master per axis, not started; one axis' master holds
what the factory opened, as its ``closers``). ``trace`` is a ``--can-log`` file
(:class:`~hil.drivers.canopen.can_log.CanLog`), given only when there is one.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import can
from can.interfaces import VALID_INTERFACES

from hil.contracts import EventSink, no_event
from hil.core.notice import warn
from hil.core.registry import Factory, SchemeRegistry, scheme_of
from hil.drivers.canopen.axes import AxisBus, AxisGroup
from hil.drivers.canopen.bus import URL_FORMS, open_can_bus, parse_can_url
from hil.drivers.canopen.can_log import CanLog
from hil.drivers.canopen.clocks import SyncClock
from hil.drivers.canopen.config import DriveMasterConfig
from hil.drivers.canopen.current_limit import CurrentLimit
from hil.drivers.canopen.identity import not_hil_emulator, read_identity
from hil.drivers.canopen.link import CanLink, FrameTrace
from hil.drivers.canopen.master import CanDriveMaster
from hil.drivers.canopen.state import MasterClock
from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.runners import LockstepDrive
from hil.emulators.drive.timebase import TIME_BASE
from hil.errors import ConfigError
from hil.protocols.cia301 import SdoAbortError
from hil.servo.config import EMULATED, AxisSpec, DriveConfig, load_drive_config
from hil.servo.drives import BusDrives

EXPECTED = f"expected emulated, ethercat://IFACE[?slave=N], {URL_FORMS}"
#: the name of the one axis of a run that names none (its topics stay /drive/...)
LONE_AXIS = "drive"


class EmulatedDrive(CanDriveMaster):
    """A master whose drive is the emulator (``emulator``, a
    :class:`~hil.emulators.drive.node.LockstepDrive`) on a private channel, in lockstep; the
    emulator is its clock. The emulated node takes the master's node id."""

    def __init__(self, master: DriveMasterConfig, emulator: DriveEmulatorConfig, *,
                 on_event: EventSink = no_event, trace: FrameTrace | None = None,
                 closers: tuple[Callable[[], None], ...] = (), url: str = EMULATED) -> None:
        self.emulator = LockstepDrive(replace(emulator, node_id=master.node_id),
                                      on_fault=fault_teller(on_event))
        super().__init__(CanLink(self.emulator.master_bus, trace=trace), master,
                         on_event=on_event, clock=self.emulator,
                         closers=(self.emulator.close, *closers), url=url)


def emulated_drives(url: str, drive: DriveConfig, axes: Sequence[AxisSpec], *,
                    on_event: EventSink = no_event,
                    trace: FrameTrace | None = None) -> BusDrives:
    """``emulated``: the drive emulator in lockstep (one node per axis), with drive.toml's
    ``[emulator]``; it is the masters' clock. A twin of an EDS says what it does not emulate
    (a warning line and an ``emulator.twin`` event)."""
    if len(axes) == 1:
        master = EmulatedDrive(axes[0].master(drive.master), drive.emulator,
                               on_event=on_event, trace=trace, closers=_closing(trace), url=url)
        _tell_twin(master.emulator, on_event)
        return BusDrives(url, [master])
    emulator = LockstepDrive(drive.emulator, node_ids=[axis.node for axis in axes],
                             on_fault=fault_teller(on_event))
    _tell_twin(emulator, on_event)
    try:
        return _grouped(url, CanLink(emulator.master_bus, trace=trace), drive, axes, on_event,
                        clock=emulator, closers=(emulator.close, *_closing(trace)))
    except BaseException:
        emulator.close()
        raise


def fault_teller(on_event: EventSink) -> Callable[[int, dict[str, Any]], None]:
    """Each fault of ``[emulator] faults`` as it starts: a ``fault.injected`` event."""
    def told(node: int, event: dict[str, Any]) -> None:
        on_event("fault.injected", f"emulator: {event['fault']} injected at drive node {node} "
                 f"t={event['t_s']:.4f} s", level="warning", source="emulator",
                 fault=event["fault"], node=node, drive_t_s=event["t_s"])
    return told


def _tell_twin(emulator: LockstepDrive, on_event: EventSink) -> None:
    """A twin of an EDS: one line of what it took from its file and what it refuses."""
    if emulator.node.config.eds is None:
        return
    summary = emulator.node.dictionary.summary(emulator.node.config.node_id)
    warn(summary)
    on_event("emulator.twin", summary, level="warning", source="emulator")


def can_drives(url: str, drive: DriveConfig, axes: Sequence[AxisSpec], *,
               on_event: EventSink = no_event, trace: FrameTrace | None = None,
               closers: tuple[Callable[[], None], ...] = ()) -> BusDrives:
    """``socketcand://...`` and every python-can ``INTERFACE://CHANNEL[?k=v]``."""
    spec = parse_can_url(url, drive.master.channel)

    def reopen() -> can.BusABC:
        return open_can_bus(spec, drive.master.bitrate)

    closers = (*closers, *_closing(trace))
    if len(axes) == 1:
        drives = BusDrives(url, [CanDriveMaster(
            CanLink(reopen(), reopen=reopen, trace=trace), axes[0].master(drive.master),
            on_event=on_event, url=url, closers=closers)])
    else:
        drives = _grouped(url, CanLink(reopen(), trace=trace), drive, axes, on_event,
                          closers=closers)
    for master in drives.masters:  # a drive that outlives the run: its settings journaled
        master.settings.keep_journal(url)
    return drives


def _grouped(url: str, link: CanLink, drive: DriveConfig, axes: Sequence[AxisSpec],
             on_event: EventSink, *, clock: MasterClock | None = None,
             closers: tuple[Callable[[], None], ...] = ()) -> BusDrives:
    """Several drives on one link: an :class:`AxisBus`, one master per axis on it."""
    nodes = [axis.node for axis in axes]
    axis_bus = AxisBus(link, nodes, master_heartbeat_id=drive.master.heartbeat_id)
    masters = [CanDriveMaster(axis_bus.node_link(axis.node), axis.master(drive.master),
                              on_event=on_event, clock=clock, url=f"{url} axis {axis.name}")
               for axis in axes]
    return BusDrives(url, masters, AxisGroup(axis_bus, masters), closers)


def _closing(trace: FrameTrace | None) -> tuple[Callable[[], None], ...]:
    close = getattr(trace, "close", None)
    return (close,) if close is not None else ()


def _python_can_interface(scheme: str) -> Factory | None:
    return can_drives if scheme in VALID_INTERFACES else None


DRIVES = SchemeRegistry(
    "drive",
    {EMULATED: ("hil.servo.rig", "emulated_drives"),
     "socketcand": ("hil.servo.rig", "can_drives"),
     "ethercat": ("hil.servo.ethercat", "ethercat_drives")},
    "hil.drive_devices",
    fallback=_python_can_interface,
)


def open_drives(url: str, drive: DriveConfig, axes: Sequence[AxisSpec], *,
                on_event: EventSink = no_event, realtime: bool = False,
                can_log: str | None = None) -> BusDrives:
    """The drives of ``axes`` on the bus at ``url`` (masters not started), through
    :data:`DRIVES`. An unknown scheme is a ConfigError naming the forms; ``can_log`` writes
    every frame of the bus to that file (python-can's formats).

    ``emulated`` with ``realtime``: the drive emulator (one node per axis) in a process of its
    own on loopback, as the hardware would be (the loop process then measures only its own
    cost), reading the run's effective tables; the process stops when the bus is released."""
    try:
        factory = DRIVES.factory(url)
    except ConfigError as exc:
        raise ConfigError(f"{exc}; {EXPECTED}") from None
    trace = CanLog(can_log, drive.master.channel) if can_log else None
    try:
        if realtime and scheme_of(url) == EMULATED:
            return emulator_process_drives(drive, axes, on_event, trace)
        # a plug-in factory that writes no --can-log is not asked to
        extra = {"trace": trace} if trace is not None else {}
        drives: BusDrives = factory(url, drive, tuple(axes), on_event=on_event, **extra)
        return drives
    except BaseException:
        if trace is not None:
            trace.close()
        raise


def open_drive(url: str | None = None, drive: DriveConfig | None = None, *,
               on_event: EventSink = no_event, realtime: bool = False,
               can_log: str | None = None) -> CanDriveMaster:
    """A master (not started) for the one drive at ``url`` (None: drive.toml's ``[bus]``), with
    ``drive`` (default: the packaged drive.toml): :func:`open_drives` for the axis of
    ``[master]``; closing the master releases everything it was opened with."""
    drive = drive or load_drive_config()
    bus = open_drives(url or drive.bus_url, drive, [lone_axis(drive)], on_event=on_event,
                      realtime=realtime, can_log=can_log)
    if len(bus.masters) != 1 or bus.closers:
        bus.disconnect()
        raise ConfigError(f"the drive factory of {url or drive.bus_url} must give one axis one "
                          "master that holds what it opened (its closers), got "
                          f"{len(bus.masters)} master(s) and {len(bus.closers)} closer(s)")
    return bus.masters[0]


def lone_axis(drive: DriveConfig) -> AxisSpec:
    """The one axis of a run that names none: ``[master]``'s node."""
    return AxisSpec(LONE_AXIS, drive.master.node_id)


def emulator_process_drives(drive: DriveConfig, axes: Sequence[AxisSpec], on_event: EventSink,
                            trace: FrameTrace | None) -> BusDrives:
    """The drives of ``axes`` on socketcand to ``hil emulate drive --harden`` started for
    them (one node per axis)."""
    from hil.emulator_process import start_drive_emulator

    # the run's effective tables, every layer in: what the run was configured with; hardened
    # as the loop is, so that the rig's side is not what runs late (its steps: the session's
    # realtime.emulator metadata)
    model = drive.emulator.axis_model
    process = start_drive_emulator(node=[axis.node for axis in axes], tables=drive.data,
                                   harden=True, model=model.source if model else None)
    granted = ", ".join(f"{step} {outcome.split(':')[0]}"
                        for step, outcome in process.hardening.items())
    on_event("emulator.process", f"drive emulator in process {process.pid} at {process.url} "
             f"(real-time: {granted or 'not reported'})", source="drive", pid=process.pid,
             url=process.url, hardening=process.hardening)
    try:
        return can_drives(process.url, drive, axes, on_event=on_event, trace=trace,
                          closers=(process.stop,))
    except BaseException:
        process.stop()
        raise


def share_lockstep_time(master: CanDriveMaster, on_event: EventSink = no_event) -> bool:
    """Lockstep over a bus: ask the drive to keep the master's time (hil's emulator's
    manufacturer object 0x2005 ``Time base``: its SYNCs' time, given up after
    ``lockstep_timeout_ms`` of wall time without a frame). When it does, the master goes by its
    SYNCs too (:class:`~hil.drivers.canopen.clocks.SyncClock`): one clock on both sides of the
    wire, which no pause can fault; the drive's own clock again when the master lets it go.
    A drive that keeps its own clock (real hardware, ``hil emulate drive --clock wall``) is
    watched on the wall clock, as in real time. Whether it does: the return value, and a
    ``drive.clock`` event. 0x2005 is written only to a drive whose identity (0x1018) is hil's
    emulator's: a vendor's drive is watched on the wall clock without being asked."""
    n, bound_ms = master.node_id, round(master.config.lockstep_timeout_s * 1e3)
    identity = read_identity(master.sdo)
    if not identity.hil_emulator:
        on_event("drive.clock", f"{not_hil_emulator(n, identity, '0x2005 time base')}: it "
                 "keeps its own clock, and lockstep watches it on the wall clock, where a "
                 "pause on either side can fault it", level="warning", source=f"drive{n}",
                 shared=False, identity=identity.as_dict())
        return False
    try:  # a setting of the run: the drive's own clock again when the master lets it go
        master.settings.write(TIME_BASE, 0, bound_ms, "<I")
    except SdoAbortError as exc:
        on_event("drive.clock", f"drive node {n} keeps its own clock ({exc}): lockstep "
                 "watches it on the wall clock, where a pause on either side can fault it",
                 level="warning", source=f"drive{n}", shared=False)
        return False
    master.clock = SyncClock(master.link, master.config.cycle_period_s)
    on_event("drive.clock", f"drive node {n} keeps the master's time: its SYNCs (a drive "
             f"silent for {bound_ms} ms of wall time is gone)", source=f"drive{n}",
             shared=True, bound_ms=bound_ms)
    return True


def keep_lockstep_time(master: CanDriveMaster, on_event: EventSink = no_event) -> None:
    """Once the drive is enabled: a drive that took the master's time
    (:func:`share_lockstep_time`) still keeps it, or is asked again, in a warning event. A
    master set up on a busy machine can be silent for longer than the bound before the drive
    is enabled: the drive, not driving, lets the time go without a fault, and the run went on
    in lockstep against a drive on its own clock, unsaid."""
    if not isinstance(master.clock, SyncClock):
        return
    n, bound_ms = master.node_id, round(master.config.lockstep_timeout_s * 1e3)
    if master.sdo.read_int(TIME_BASE, 0, "<I") == bound_ms:
        return
    master.sdo.write(TIME_BASE, 0, bound_ms, "<I")  # journaled when share_lockstep_time wrote it
    on_event("drive.clock", f"drive node {n} had let the master's time go while the run was "
             f"set up (nothing sent for over {bound_ms} ms of wall time: a busy machine); it "
             "keeps it again from here", level="warning", source=f"drive{n}", shared=True,
             bound_ms=bound_ms, taken_again=True)


def reach(master: CanDriveMaster, on_event: EventSink, reset_fault: bool,
          asked: str = "master.current_limit_mA") -> None:
    """Reach ``master``'s drive and leave it not enabled: over a bus in lockstep, one clock
    on both sides of the wire; a FAULT cleared when ``reset_fault``; opened, and what it
    lacks, what an earlier run left on it and a current limit cut below the one ``asked``
    (``--umax`` or the key) said on the terminal."""
    if master.config.lockstep:
        share_lockstep_time(master, on_event)
    if reset_fault:
        master.fault_reset()
    master.open()
    tell_notices(master)
    tell_opened(master, asked, on_event)


def tell_notices(master: CanDriveMaster) -> None:
    """What the run does differently because of the drive (an object it lacks, a limit it
    cannot be given), on the terminal (the events are recorded)."""
    for line in master.notices.take():
        warn(line)


def tell_opened(master: CanDriveMaster, asked: str, on_event: EventSink = no_event) -> None:
    """What opening the drive found that the person at the terminal must hear of, a line each:
    settings an earlier run left on it, put back (the master's event says it too), and the
    current limit cut below the one asked for (``asked``: what asked for it, ``--umax`` or
    the key), with the limit that cut it (a ``current.limit_cut`` event too)."""
    if master.settings.restored is not None:
        warn(master.settings.restored)
    cut = limit_cut(master.limit, asked)
    if cut is not None:
        warn(f"drive node {master.node_id}: {cut}")
        on_event("current.limit_cut", f"drive node {master.node_id}: {cut}", level="warning",
                 source=f"drive{master.node_id}", **master.limit.describe())


def limit_cut(limit: CurrentLimit, asked: str) -> str | None:
    """``current limit: asked 12000 mA (--umax), applied 1000 mA: the drive's max torque
    (0x6072) 1000 mA cuts it``; None when the limit asked for is the one applied."""
    if limit.applied_ma >= limit.run_ma:
        return None
    cutting = " and ".join(f"the drive's {name} {value:g} mA" for name, value in (
        ("max current (0x6073)", limit.max_current_ma),
        (f"max torque ({limit.max_torque_from})", limit.max_torque_ma))
        if value == limit.applied_ma)
    return (f"current limit: asked {limit.run_ma:g} mA ({asked}), applied "
            f"{limit.applied_ma:g} mA: {cutting} cuts it")
