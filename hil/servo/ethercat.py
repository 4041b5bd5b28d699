"""``ethercat://IFACE?slave=N``: CiA 402 drives on an EtherCAT segment (the ``ethercat`` extra,
SOEM through pysoem). One segment per URL; each axis is a slave position (``?slave=N`` for a
lone axis, else each axis' number: ``--axes x=1,y=2``). Several axes on a segment share its
frame: cycling together, one LRW carries every axis' set point (:class:`SegmentAxes`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from urllib.parse import parse_qsl

from hil.contracts import EventSink, no_event
from hil.drivers.canopen.link import FrameTrace
from hil.drivers.ethercat.master import EthercatDriveMaster
from hil.drivers.ethercat.segment import Segment
from hil.errors import ConfigError
from hil.servo.config import AxisSpec, DriveConfig
from hil.servo.drives import BusDrives

URL_FORM = "ethercat://IFACE[?slave=N]"


def parse_ethercat_url(url: str) -> tuple[str, int | None]:
    """The interface and the slave position (None: not given) of ``ethercat://IFACE?slave=N``."""
    _, _, rest = url.partition("://")
    iface, _, query = rest.partition("?")
    if not iface or "/" in iface:
        raise ConfigError(f"drive {url!r}: expected {URL_FORM} (a network interface name)")
    try:
        options = dict(parse_qsl(query, strict_parsing=bool(query)))
    except ValueError:
        raise ConfigError(f"drive {url!r}: expected {URL_FORM}") from None
    unknown = sorted(set(options) - {"slave"})
    if unknown:
        raise ConfigError(f"drive {url!r}: unknown option {unknown[0]!r} (known: slave)")
    slave = options.get("slave")
    if slave is None:
        return iface, None
    if not slave.isdigit() or int(slave) < 1:
        raise ConfigError(f"drive {url!r}: slave must be a position 1, 2, ... (the first slave "
                          f"after the master is 1), got {slave!r}")
    return iface, int(slave)


@dataclass
class SegmentAxes:
    """Several masters on one segment, cycled together (the :class:`BusDrives` group)."""

    bus: Segment
    masters: list[EthercatDriveMaster]


def ethercat_drives(url: str, drive: DriveConfig, axes: Sequence[AxisSpec], *,
                    on_event: EventSink = no_event,
                    trace: FrameTrace | None = None) -> BusDrives:
    """The drives of ``axes`` on the segment at ``url``, one master per axis (not started);
    the segment closes with the last of them."""
    if trace is not None:
        raise ConfigError("--can-log writes CAN frames: an EtherCAT segment carries none")
    iface, slave = parse_ethercat_url(url)
    if slave is not None and len(axes) > 1:
        raise ConfigError(f"drive {url!r}: ?slave=N names one axis' slave; several axes name "
                          "theirs: --axes x=1,y=2 (slave positions)")
    positions = [slave] if slave is not None else [axis.node for axis in axes]
    segment = Segment(iface, url.partition("?")[0])
    masters = []
    try:
        for axis, position in zip(axes, positions, strict=True):
            label = url if len(axes) == 1 else f"{url} axis {axis.name}"
            config = replace(axis.master(drive.master), node_id=position)  # named by it
            masters.append(EthercatDriveMaster(
                segment, position, config, on_event=on_event, url=label,
                closers=(segment.use(),)))
    except BaseException:
        segment.close()
        raise
    for master in masters:  # a drive that outlives the run: its settings journaled
        master.settings.keep_journal(url)
    group = SegmentAxes(segment, masters) if len(masters) > 1 else None
    return BusDrives(url, list(masters), group)
