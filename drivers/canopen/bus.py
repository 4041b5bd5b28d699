"""A CAN bus named by a URL, opened through python-can (any interface it knows) or hil's own
socketcand client.

``INTERFACE://CHANNEL[?key=value&...]``: INTERFACE is a python-can interface name
(``socketcan``, ``pcan``, ``kvaser``, ``slcan``, ``gs_usb``, ``udp_multicast``, ``virtual``,
...), CHANNEL is what python-can calls the channel, written as it is (a device path keeps its
leading ``/``: ``slcan:///dev/ttyACM0``), and every query key becomes a keyword argument of
``can.Bus`` with its type read from its text (``1000000`` an int, ``0.5`` a float, ``true`` /
``false`` a bool, anything else a string): ``udp_multicast://239.0.0.1?port=43113``,
``slcan:///dev/ttyACM0?bitrate=1000000``, ``pcan://PCAN_USBBUS1?fd=true``.
``socketcand://HOST:PORT[/CHANNEL]`` reaches a socketcand gateway with hil's own client
(:class:`hil.drivers.socketcand_bus.SocketcandBus`, one TCP write per cycle).

The same bus in a config file is ``[bus]``: ``interface``, ``channel``, ``bitrate`` and a table
``options`` (:class:`CanBusSpec`).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qsl

import can
from can.interfaces import VALID_INTERFACES

from hil.drivers.canopen.errors import DriveLinkLostError, one_line
from hil.drivers.errors import DriverSetupError
from hil.drivers.socketcand_bus import SocketcandBus

SOCKETCAND = "socketcand"
_INTERFACE_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
_HOST_PORT = re.compile(r"^(?P<host>[^:/?]+):(?P<port>\d+)(?:/(?P<channel>[^?]*))?$")
URL_FORMS = ("socketcand://HOST:PORT[/CHANNEL] or INTERFACE://CHANNEL[?key=value&...] with "
             "INTERFACE one of python-can's: " + ", ".join(sorted(VALID_INTERFACES)))


@dataclass(frozen=True)
class CanBusSpec:
    """A CAN bus: python-can's interface name, its channel, and the keyword arguments of
    ``can.Bus`` (socketcand: ``host`` and ``port``)."""

    interface: str
    channel: str
    options: Mapping[str, Any] = field(default_factory=dict)

    @property
    def url(self) -> str:
        """The bus as a URL (what errors and events name)."""
        if self.interface == SOCKETCAND:
            return f"socketcand://{self.options.get('host')}:{self.options.get('port')}/" \
                   f"{self.channel}"
        query = "&".join(f"{k}={_text(v)}" for k, v in self.options.items())
        return f"{self.interface}://{self.channel}" + (f"?{query}" if query else "")


def _text(value: Any) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def typed(text: str) -> Any:
    """A query value as the type its text reads as: int, float, bool, else the string."""
    lowered = text.lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def parse_can_url(url: str, default_channel: str = "can0") -> CanBusSpec:
    """The :class:`CanBusSpec` of a CAN URL; a :class:`DriverSetupError` names what is wrong and
    the forms."""
    interface, sep, rest = url.partition("://")
    if not sep or not interface:
        raise DriverSetupError(f"drive {url!r}: expected {URL_FORMS}")
    if not _INTERFACE_NAME.match(interface) or interface not in VALID_INTERFACES:
        raise DriverSetupError(f"drive {url!r}: {interface!r} is not a python-can interface "
                          f"(known: {', '.join(sorted(VALID_INTERFACES))})")
    where, _, query = rest.partition("?")
    try:
        pairs = parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query))
    except ValueError:
        raise DriverSetupError(f"drive {url!r}: the options must be key=value pairs joined by "
                          "'&'") from None
    options: dict[str, Any] = {}
    for key, value in pairs:
        if not key.isidentifier():
            raise DriverSetupError(f"drive {url!r}: option {key!r} is not a keyword name")
        if key in options:
            raise DriverSetupError(f"drive {url!r}: option {key!r} given twice")
        if key in ("interface", "channel"):
            raise DriverSetupError(f"drive {url!r}: {key} is the URL's own part, not an option")
        options[key] = typed(value)
    if interface == SOCKETCAND:
        match = _HOST_PORT.match(where)
        if match is None:
            raise DriverSetupError(f"drive {url!r}: expected socketcand://HOST:PORT[/CHANNEL]")
        options |= {"host": match["host"], "port": int(match["port"])}
        return CanBusSpec(SOCKETCAND, match["channel"] or default_channel, options)
    if not where:
        raise DriverSetupError(f"drive {url!r}: no channel (expected {interface}://CHANNEL, e.g. "
                          f"{interface}://can0 or {interface}:///dev/ttyACM0)")
    return CanBusSpec(interface, where, options)


def open_can_bus(spec: CanBusSpec, bitrate: int | None = None) -> can.BusABC:
    """The bus of ``spec`` (``bitrate`` added unless its options set one). A bus that cannot
    be opened - the interface not installed, no such channel, a refused option - is a
    DriveLinkLostError naming the interface, the channel and python-can's reason."""
    options = dict(spec.options)
    if spec.interface == SOCKETCAND:
        try:
            return SocketcandBus(spec.channel, options["host"], options["port"])
        except can.CanError as exc:  # its message names the gateway and the bus
            raise DriveLinkLostError(one_line(exc)) from None
    if bitrate is not None:
        options.setdefault("bitrate", bitrate)
    try:
        return can.Bus(interface=spec.interface, channel=spec.channel, **options)
    except (can.CanError, OSError, ValueError, TypeError, ImportError, KeyError) as exc:
        raise DriveLinkLostError(f"cannot open CAN interface {spec.interface!r} channel "
                                 f"{spec.channel!r}: {one_line(exc)}") from None
